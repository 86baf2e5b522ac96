"""Data-parallel training under ``torchrun --nproc_per_node N`` (DistributedDataParallel): one
process per GPU (NCCL), or several CPU processes (gloo). Without torchrun (WORLD_SIZE unset or
1) every function here is a no-op and training runs in one process as before.

torchrun's agent ends every process of the job when one of them dies, and each training step
exchanges gradients, so a crashed process cannot leave the others waiting for long."""
from __future__ import annotations

import os
from datetime import timedelta


def init_from_env(device: str) -> tuple[int, int]:
    """Join the process group torchrun describes (WORLD_SIZE > 1); returns (rank, world size)."""
    n = int(os.environ.get("WORLD_SIZE", "1"))
    if n <= 1:
        return 0, 1
    import torch
    import torch.distributed as dist
    if not dist.is_initialized():
        if device == "cuda":
            torch.cuda.set_device(int(os.environ.get("LOCAL_RANK", "0")))
        dist.init_process_group("nccl" if device == "cuda" else "gloo", timeout=timedelta(minutes=30))
    return dist.get_rank(), dist.get_world_size()


def world() -> tuple[int, int]:
    """(rank, world size) of this process; (0, 1) outside a process group."""
    import torch.distributed as dist
    if dist.is_available() and dist.is_initialized():
        return dist.get_rank(), dist.get_world_size()
    return 0, 1


def _max_all(value: float, dtype: str) -> float:
    """The largest of every process's ``value``, on every process (``value`` itself outside a group)."""
    if world()[1] == 1:
        return value
    import torch
    import torch.distributed as dist
    t = torch.tensor([value], dtype=getattr(torch, dtype))
    if dist.get_backend() == "nccl":
        t = t.cuda()
    dist.all_reduce(t, op=dist.ReduceOp.MAX)
    return t.item()


def any_rank(flag: bool) -> bool:
    """True on every process when ``flag`` is true on any (all stop together, or none does)."""
    return bool(_max_all(1 if flag else 0, "int32"))


def max_over_ranks(value: float) -> float:
    """The largest of every process's ``value`` (one clock for all: a step size set from the time
    spent must be the same on every process, or their replicas drift apart)."""
    return float(_max_all(float(value), "float64"))


def barrier() -> None:
    if world()[1] > 1:
        import torch.distributed as dist
        dist.barrier()


def first_then_rest(make):
    """``make()`` on the first process, then on the others once it is done: the first writes a
    cache (crops, a detection set) that the others then read instead of making it again."""
    rank = world()[0]
    out = make() if rank == 0 else None
    barrier()
    return make() if rank != 0 else out


def finish() -> None:
    """Leave the process group (at the end of a distributed run), all processes together. The
    first saves a checkpoint before it gets here; a process that left while its peer was still
    busy was the likely cause of a SIGABRT of the second process in CI (gloo's transport
    thread; its message was lost, and 24 runs here did not repeat it)."""
    import torch.distributed as dist
    if dist.is_available() and dist.is_initialized():
        barrier()
        dist.destroy_process_group()
