"""Autoencoder training loop (torch; a CUDA GPU when asked for, else the CPU): AdamW, a step size
cut on validation plateaus (or annealed over the time budget), early stopping on the validation
L2, the thesis's online augmentations, checkpoints and resume."""
from __future__ import annotations

import math
import pickle
import time
from pathlib import Path

import numpy as np
import torch
from torch.nn import functional as F
from tqdm import tqdm

from tracker.core.defaults import LR_SCHEDULES
from tracker.core.errors import UserError
from tracker.core.files import write_whole
from tracker.training.nets import precision as prec
from tracker.training.nets.autoencoder import AutoEncoder, loss_terms
from tracker.training.nets.schedule import budget_lr

KL_ALPHA = 0.1  # Table 4.6
# a checkpoint inside an epoch at least this often (an epoch of 150 k crops takes 20 min on a CPU):
# a process killed without warning loses at most this much training
CHECKPOINT_SECONDS = 300.0


def to_tensor(u8: np.ndarray) -> torch.Tensor:
    """(N, S, S, 3) uint8 RGB -> (N, 3, S, S) float in [0, 1]."""
    return torch.from_numpy(u8).permute(0, 3, 1, 2).float().div_(255.0)


def augment(x: torch.Tensor, g: torch.Generator, p: float = 0.3) -> torch.Tensor:
    """Thesis 4.3.5, each with probability p per image: colour jitter (brightness and
    contrast 0.4-2.3, saturation 0.8-1.2), Gaussian blur (5x5, sigma 0.1-1.2), random
    affine (translate 0.1, scale 0.9-1.1)."""
    B = x.shape[0]

    def pick():
        return torch.rand(B, generator=g) < p

    def U(lo, hi, n=B):
        return lo + (hi - lo) * torch.rand(n, generator=g)

    m = pick()
    if m.any():
        xb = x[m]
        n = xb.shape[0]
        xb = xb * U(0.4, 2.3, n)[:, None, None, None] ** 0.5  # brightness (range softened: sqrt)
        mean = xb.mean(dim=(1, 2, 3), keepdim=True)
        xb = (xb - mean) * U(0.4, 2.3, n)[:, None, None, None] ** 0.5 + mean  # contrast
        grey = xb.mean(dim=1, keepdim=True)
        xb = (xb - grey) * U(0.8, 1.2, n)[:, None, None, None] + grey  # saturation
        x = x.clone()
        x[m] = xb.clamp(0, 1)
    m = pick()
    if m.any():
        sig = float(U(0.1, 1.2, 1))
        k = torch.exp(-(torch.arange(5) - 2.0) ** 2 / (2 * sig * sig))
        k = (k / k.sum()).float()
        kern = (k[:, None] * k[None, :])[None, None].repeat(3, 1, 1, 1)
        x = x.clone()
        x[m] = F.conv2d(F.pad(x[m], (2, 2, 2, 2), mode="replicate"), kern, groups=3)
    m = pick()
    if m.any():
        n = int(m.sum())
        s = U(0.9, 1.1, n)
        theta = torch.zeros(n, 2, 3)
        theta[:, 0, 0] = 1 / s
        theta[:, 1, 1] = 1 / s
        theta[:, :, 2] = U(-0.2, 0.2, 2 * n).view(n, 2)  # translate 0.1 of the size (grid units: 2)
        grid = F.affine_grid(theta, list(x[m].shape), align_corners=False)
        x = x.clone()
        x[m] = F.grid_sample(x[m], grid, padding_mode="zeros", align_corners=False)
    return x


class CachedInputs:
    """A frozen front's outputs for every crop (the encoder's ``frozen`` part), float16 in a
    memory-mapped .npy of shape (1 + A, N, C, h, w): version 0 from the crop as cut, versions
    1..A from the crop under ``augment`` (drawn once, when cached). Training takes a random
    augmented version of each crop per step, validation and encoding version 0: the frozen part
    then costs nothing per step (no forward, no backward). ``rows``: the crops of a subset."""

    def __init__(self, path, rows=None):
        self.path = Path(path)
        self.arr = np.load(self.path, mmap_mode="r")
        self.rows = np.arange(self.arr.shape[1]) if rows is None else np.asarray(rows)

    def __len__(self) -> int:
        return len(self.rows)

    @property
    def versions(self) -> int:
        return self.arr.shape[0]

    def subset(self, rows) -> "CachedInputs":
        return CachedInputs(self.path, self.rows[np.asarray(rows)])

    def batch(self, idx, g: torch.Generator | None = None) -> torch.Tensor:
        """Crops ``idx`` (of this subset): version 0, or with ``g`` a random augmented one each."""
        rows = self.rows[np.asarray(idx)]
        if g is None or self.versions == 1:
            ver = np.zeros(len(rows), np.int64)
        else:
            ver = 1 + torch.randint(self.versions - 1, (len(rows),), generator=g).numpy()
        return torch.from_numpy(np.asarray(self.arr[ver, rows], dtype=np.float32))


@torch.no_grad()
def cache_frozen_outputs(frozen: torch.nn.Module, x_u8: np.ndarray, path, n_aug: int = 3, seed: int = 0,
                         batch: int = 256, log=print) -> CachedInputs:
    """Run ``frozen`` over every crop (as cut, then ``n_aug`` augmented versions) into ``path``
    (written whole: a half-written cache is never read)."""
    from tracker.core.files import write_whole
    frozen.eval()
    g = torch.Generator().manual_seed(seed + 7919)
    probe = frozen(to_tensor(x_u8[:1]))
    shape = (1 + n_aug, len(x_u8)) + tuple(probe.shape[1:])
    t0 = time.perf_counter()

    def fill(tmp):
        arr = np.lib.format.open_memmap(tmp, mode="w+", dtype=np.float16, shape=shape)
        for v in range(1 + n_aug):
            for i in range(0, len(x_u8), batch):
                x = to_tensor(x_u8[i:i + batch])
                arr[v, i:i + len(x)] = frozen(augment(x, g) if v else x).numpy().astype(np.float16)
        arr.flush()
        del arr

    write_whole(Path(path), fill)
    log(f"cached the frozen front's outputs {shape[2:]} for {len(x_u8)} crops x {1 + n_aug} versions "
        f"({time.perf_counter() - t0:.0f} s, {np.prod(shape) * 2 / 1e9:.2f} GB)")
    return CachedInputs(path)


class Rows:
    """Rows ``rows`` of ``arr``, taken when indexed (``Rows(a, r)[i] == a[r[i]]``): a training
    split of the crops without copying them (a copy per split doubled the encoder stage's memory)."""

    def __init__(self, arr: np.ndarray, rows):
        self.arr, self.rows = arr, np.asarray(rows)

    def __len__(self) -> int:
        return len(self.rows)

    def __getitem__(self, idx) -> np.ndarray:
        return self.arr[self.rows[idx]]


def batch_inputs(x, idx, g: torch.Generator | None = None) -> torch.Tensor:
    """The network's input for crops ``idx``: uint8 images (augmented with ``g``) or cached
    frozen-front outputs (a random augmented version with ``g``)."""
    if isinstance(x, CachedInputs):
        return x.batch(idx, g)
    t = to_tensor(x[idx])
    return augment(t, g) if g is not None else t


def rng_states(device: str) -> dict:
    """torch's own generators (the variational latent's noise draws from them), to checkpoint."""
    return {"cpu": torch.get_rng_state(), **({"cuda": torch.cuda.get_rng_state()} if device == "cuda" else {})}


def set_rng_states(states: dict, device: str) -> None:
    torch.set_rng_state(states["cpu"])
    if device == "cuda" and "cuda" in states:
        torch.cuda.set_rng_state(states["cuda"])


def kl_weight(step: int, warmup: int = 0) -> float:
    """The KL term's weight at training step ``step``: ``KL_ALPHA``, reached linearly from 0
    over the first ``warmup`` steps when ``warmup`` > 0."""
    return KL_ALPHA * (min(1.0, step / warmup) if warmup > 0 else 1.0)


def onehot(obj_idx: np.ndarray, n: int) -> torch.Tensor:
    return F.one_hot(torch.from_numpy(obj_idx).long(), n).float()


def _flushing_subnormals(fn):
    """Run ``fn`` with subnormal floats flushed to zero (tiny activations and gradients take a
    slow path on x86 CPUs: a run crawled at 6-8 s per batch without it), and put the process's
    IEEE behaviour back afterwards: other code (hypothesis, numpy users) relies on it."""
    import functools

    @functools.wraps(fn)
    def wrapped(*a, **k):
        torch.set_flush_denormal(True)
        try:
            return fn(*a, **k)
        finally:
            torch.set_flush_denormal(False)
    return wrapped


@_flushing_subnormals
def train_autoencoder(model: AutoEncoder, x_tr, y_tr, c_tr, x_va, y_va, c_va, out_dir: Path,
                      minutes: float = 45.0, batch: int = 128, lr: float = 1e-3, patience: int = 50,
                      seed: int = 0, init_from=None, precision: str = "fp32", max_epochs: int = 1000,
                      log=print, device: str = "cpu", kl_warmup: int = 0, lr_schedule: str = "plateau",
                      max_steps: int | None = None) -> dict:
    """Train until the time budget (or the step budget), early stopping, or ``max_epochs``. Resumes from
    ``out_dir/ae_checkpoint.pt`` when it exists; otherwise ``init_from`` (another run's
    checkpoint) gives the starting weights and optimiser state, with a fresh budget, history
    and best validation loss (the validation crops differ). ``precision`` ('auto', 'bf16' or
    'fp32', see ``precision.resolve``) is the arithmetic of the training passes; validation is float32.
    ``device``: 'cpu' or 'cuda' (resolved already); batches are cut and augmented on the CPU.
    ``kl_warmup``: the KL term's weight rises linearly from 0 to ``KL_ALPHA`` over this many
    steps (0: full weight from the first step).
    ``lr_schedule``: 'budget' anneals the step size by a cosine over ``minutes`` (to 2 % of
    ``lr`` at the end); 'plateau' divides it by 5 after 3 epochs without a better validation L2.
    ``max_steps``: a budget of training steps (batches) instead of time: training ends after that
    many, however long they take (``minutes`` then ends nothing, and 'budget' anneals over the
    steps), so a seed gives the same run on any machine. Steps are counted as the KL warm-up
    counts them: a resumed run's earlier epochs count whole (one that a budget ended part-way,
    then validated, is done, as with a time budget).
    A checkpoint is written after every epoch, every ``CHECKPOINT_SECONDS`` within one, and on
    Ctrl-C (or SIGTERM made Ctrl-C), which is then raised again; a resumed run goes on from the
    batch it stopped at, with the same order of crops and random draws. Returns the training history."""
    from tracker.training.nets import distributed as dd
    rank, n_proc = dd.world()  # several processes under torchrun: each takes its share of every batch
    if lr_schedule not in LR_SCHEDULES:
        raise UserError(f"unknown step-size schedule '{lr_schedule}' (choose from {', '.join(LR_SCHEDULES)})")
    if max_steps is not None and not (isinstance(max_steps, int) and max_steps >= 1):
        raise UserError(f"the step budget must be a whole number of at least 1, not {max_steps}")
    torch.manual_seed(seed)
    model.to(device)
    net = model
    if n_proc > 1:
        from torch.nn.parallel import DistributedDataParallel
        net = DistributedDataParallel(model, device_ids=[torch.cuda.current_device()] if device == "cuda" else None)
        log = log if rank == 0 else (lambda *a, **k: None)
    g = torch.Generator().manual_seed(seed)
    opt = torch.optim.AdamW(model.parameters(), lr=lr, betas=(0.9, 0.999), eps=1e-8, weight_decay=1e-2)
    sched = torch.optim.lr_scheduler.ReduceLROnPlateau(opt, factor=0.2, patience=3, min_lr=1e-6)
    ckpt = Path(out_dir) / "ae_checkpoint.pt"
    best_path = Path(out_dir) / "ae_best.pt"
    hist = {"epoch": [], "train_l2": [], "val_l2": [], "lr": [], "seconds": []}
    start_epoch, best, since_best, spent = 0, math.inf, 0, 0.0
    part = None  # an epoch a checkpoint left part-way: its order of crops, batches done and L2 sums
    source = ckpt if ckpt.is_file() else (Path(init_from) if init_from else None)
    if source is not None:
        try:
            st = torch.load(source, weights_only=True, map_location="cpu")  # tensors and containers only: no code runs
            model.load_state_dict(st["model"])
            opt.load_state_dict(st["opt"])
            sched.load_state_dict(st["sched"])
        except FileNotFoundError:
            raise UserError(f"{source}: no such checkpoint (--init-from takes an ae_checkpoint.pt)") from None
        except (RuntimeError, KeyError, ValueError, TypeError, EOFError, pickle.UnpicklingError) as e:
            hint = (f"delete {Path(out_dir)} to start afresh, or train into another --out" if source == ckpt
                    else "--init-from must come from a run with the same --method, --encoder, --size, --latent and objects")
            raise UserError(f"{source} is the checkpoint of another network ({type(e).__name__}): {hint}") from None
        g.set_state(st["gen"])
        if source == ckpt:
            if "rng" in st:  # the latent's sampling noise goes on as it would have
                set_rng_states(st["rng"], device)
            part = st.get("part")
            start_epoch = st["epoch"] + (0 if part else 1)
            best, since_best, hist, spent = st["best"], st["since_best"], st["hist"], st["spent"]
            at = f", batch {part['pos']}" if part else ""
            log(f"resumed from {ckpt} at epoch {start_epoch}{at} ({spent / 60:.1f} min spent, best val L2 {best:.2f})")
        else:
            sched.best, sched.num_bad_epochs = sched.mode_worse, 0  # judged afresh on this run's validation crops
            log(f"started from the weights of {source} (epoch {st['epoch']}, {st['spent'] / 60:.1f} min there); "
                f"new budget, history and best validation L2")
    if ckpt.is_file() and init_from:
        log("--init-from ignored: resuming this run's own checkpoint")
    variational = model.encoder.variational
    cond = model.n_cond > 0
    precision = prec.resolve(precision, device)  # 'auto' too; once, not per batch
    prec.channels_last(model)
    n = len(x_tr)
    t_start = time.perf_counter() - spent
    if n_proc > 1:  # one order of the crops for all processes; augmentation draws of each its own
        g = torch.Generator().manual_seed(seed * 1000 + rank)

    def save(epoch: int, spent: float, part: dict | None = None) -> None:
        if rank == 0:  # one checkpoint, the first process's (the weights are the same in all)
            state = {"model": model.state_dict(), "opt": opt.state_dict(), "sched": sched.state_dict(),
                     "gen": g.get_state(), "epoch": epoch, "best": best, "since_best": since_best,
                     "hist": hist, "spent": spent, "rng": rng_states(device), **({"part": part} if part else {})}
            write_whole(ckpt, lambda tmp: torch.save(state, tmp))

    def save_part():
        save(epoch, time.perf_counter() - t_start, {"perm": torch.from_numpy(perm), "pos": pos, "tot": tot, "cnt": cnt})

    last_save = time.perf_counter()
    for epoch in range(start_epoch, max_epochs):
        model.train()
        if part:
            perm, pos, tot, cnt = part["perm"].numpy(), part["pos"], part["tot"], part["cnt"]
            part = None
        else:
            perm = (torch.randperm(n, generator=g) if n_proc == 1
                    else torch.randperm(n, generator=torch.Generator().manual_seed(seed * 100003 + epoch))).numpy()
            pos, tot, cnt = 0, 0.0, 0
        # every process takes the same number of steps (a partial last batch too small to share is left out)
        starts = [i for i in range(0, n, batch) if min(batch, n - i) >= n_proc]
        if max_steps is not None and epoch * len(starts) + pos >= max_steps:  # a resumed run done already
            break
        bar = tqdm(total=len(starts), initial=pos, desc=f"epoch {epoch}", unit="batch", leave=False,
                   disable=rank != 0)
        try:
            for step, i in enumerate(starts[pos:], start=epoch * len(starts) + pos):
                idx = np.sort(perm[i:i + batch][rank::n_proc])
                xb = prec.channels_last(batch_inputs(x_tr, idx, g).to(device))
                yb = to_tensor(y_tr[idx]).to(device)
                cb = c_tr[idx].to(device) if cond else None
                if lr_schedule == "budget":  # one clock: the same step size on every process under torchrun
                    frac = (step / max_steps if max_steps is not None
                            else dd.max_over_ranks(time.perf_counter() - t_start) / (minutes * 60))
                    step_lr = budget_lr(lr, frac, step)
                    for gr in opt.param_groups:
                        gr["lr"] = step_lr
                with prec.autocast(precision, device):
                    recon, mu, logvar = net(xb, cb)
                l2, kl = loss_terms(recon, yb, mu, logvar)
                loss = l2 + (kl_weight(step, kl_warmup) * kl if variational else 0.0)
                opt.zero_grad(set_to_none=True)
                loss.backward()
                opt.step()
                tot += float(l2.detach()) * len(idx)
                cnt += len(idx)
                pos += 1
                bar.update(1)
                bar.set_postfix(l2=f"{tot / cnt:.1f}")
                if time.perf_counter() - last_save > CHECKPOINT_SECONDS:
                    save_part()
                    last_save = time.perf_counter()
                if dd.any_rank(step + 1 >= max_steps if max_steps is not None
                               else time.perf_counter() - t_start > minutes * 60):
                    break
            bar.close()
            val = evaluate_l2(model, x_va, y_va, c_va if cond else None, batch=256)
        except KeyboardInterrupt:
            bar.close()
            save_part()
            log(f"interrupted: checkpoint saved in {ckpt} (epoch {epoch}, batch {pos} of {len(starts)}); "
                f"rerun the same command to resume")
            raise
        if lr_schedule == "plateau":
            sched.step(val)
        spent = time.perf_counter() - t_start
        for k, v in zip(hist, (epoch, tot / max(cnt, 1), val, opt.param_groups[0]["lr"], spent)):
            hist[k].append(v)
        improved = val < best  # the same on every process: the same weights, the same crops
        if improved:
            best, since_best = val, 0
            if rank == 0:
                torch.save(model.state_dict(), best_path)
        else:
            since_best += 1
        log(f"epoch {epoch}: train L2 {tot / max(cnt, 1):.2f}, val L2 {val:.2f}{' *' if improved else ''}, "
            f"lr {opt.param_groups[0]['lr']:.1e}, {spent / 60:.1f} min")
        save(epoch, spent)
        last_save = time.perf_counter()
        over = epoch * len(starts) + pos >= max_steps if max_steps is not None else spent > minutes * 60
        if dd.any_rank(since_best >= patience or over):
            break
    dd.barrier()  # the best weights are written
    model.load_state_dict(torch.load(best_path, weights_only=True, map_location=device))
    model.to(memory_format=torch.contiguous_format)
    return hist


@torch.no_grad()
def evaluate_l2(model, x, y, c=None, batch=256) -> float:
    model.eval()
    dev = next(model.parameters()).device
    tot = 0.0
    for i in range(0, len(x), batch):
        xb = batch_inputs(x, np.arange(i, min(i + batch, len(x))))
        recon, mu, logvar = model(xb.to(dev), None if c is None else c[i:i + batch].to(dev))
        tot += float(((recon - to_tensor(y[i:i + batch]).to(dev)) ** 2).flatten(1).sum(1).sum())
    return tot / max(len(x), 1)


@torch.no_grad()
def encode_all(model, x, c=None, batch=512) -> np.ndarray:
    model.eval()
    dev = next(model.parameters()).device
    out = [model.encoder(to_tensor(x[i:i + batch]).to(dev), None if c is None else c[i:i + batch].to(dev)).cpu().numpy()
           for i in range(0, len(x), batch)]
    return np.concatenate(out).astype(np.float32)
