"""Writing a training checkpoint whole or not at all: a Ctrl-C or a kill during the write leaves
the previous checkpoint in place, never a truncated file that the next run cannot resume."""
from pathlib import Path


def save_whole(obj, path) -> None:
    import torch
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    torch.save(obj, tmp)
    tmp.replace(path)
