"""Fitting the pose head's regressors (scikit-learn, torch). Each class here adds ``fit`` to
its predict-only run-time counterpart in :mod:`tracker.runtime.heads`, which is what a bundle
stores and loads."""
from __future__ import annotations

import time

import numpy as np

from tracker.runtime.heads import MLP, DistanceKNN, Trees


class NumpyMLP(MLP):
    """A SiLU MLP trained with torch, evaluated with numpy. ``loss``: 'l1_rotation' (input
    -> 6D, L1 between rotation matrices, minimum over the object's symmetries) or 'l1'."""

    def __init__(self, hidden=(256, 256), loss="l1", epochs=300, lr=3e-3, batch=1024, weight_decay=1e-4,
                 seed=0, minutes=5.0):
        self.hidden, self.loss, self.epochs, self.lr, self.batch = hidden, loss, epochs, lr, batch
        self.weight_decay, self.seed, self.minutes = weight_decay, seed, minutes

    def fit(self, X, Y, sym_R=None, X_val=None, Y_val=None, sym_val=None, log=None):
        """``Y``: (N, 3, 3) rotations for 'l1_rotation', else (N, D). ``sym_R``: (N, S, 3, 3)
        symmetry rotations per sample (identity first) for the rotation loss. With a
        validation set, the weights of the epoch with the lowest validation loss are kept
        (checked every 5 epochs): the latent codes are few and an MLP overfits them."""
        import torch
        torch.manual_seed(self.seed)
        X = np.asarray(X, dtype=np.float32)
        self.mean_ = X.mean(0)
        self.scale_ = X.std(0) + 1e-6
        Xt = torch.from_numpy((X - self.mean_) / self.scale_)
        Yt = torch.from_numpy(np.asarray(Y, dtype=np.float32))
        St = torch.from_numpy(np.asarray(sym_R, dtype=np.float32)) if sym_R is not None else None
        dout = 6 if self.loss == "l1_rotation" else Yt.shape[1]
        dims = [X.shape[1], *self.hidden, dout]
        mods = []
        for i in range(len(dims) - 1):
            mods.append(torch.nn.Linear(dims[i], dims[i + 1]))
            if i < len(dims) - 2:
                mods.append(torch.nn.SiLU())
        net = torch.nn.Sequential(*mods)
        opt = torch.optim.AdamW(net.parameters(), lr=self.lr, weight_decay=self.weight_decay)
        sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, self.epochs)
        g = torch.Generator().manual_seed(self.seed)
        t0 = time.perf_counter()
        if X_val is not None:
            Xv = torch.from_numpy((np.asarray(X_val, dtype=np.float32) - self.mean_) / self.scale_)
            Yv = torch.from_numpy(np.asarray(Y_val, dtype=np.float32))
            Sv = torch.from_numpy(np.asarray(sym_val, dtype=np.float32)) if sym_val is not None else None
        best, best_state = np.inf, None
        self.best_epoch_ = None
        for ep in range(self.epochs):
            perm = torch.randperm(len(Xt), generator=g)
            for i in range(0, len(Xt), self.batch):
                idx = perm[i:i + self.batch]
                out = net(Xt[idx])
                loss = self._loss(torch, out, Yt[idx], None if St is None else St[idx])
                opt.zero_grad(set_to_none=True)
                loss.backward()
                opt.step()
            sched.step()
            if X_val is not None and ep % 5 == 4:
                with torch.no_grad():
                    v = float(self._loss(torch, net(Xv), Yv, Sv))
                if v < best:
                    best, self.best_epoch_ = v, ep
                    best_state = {k: t.clone() for k, t in net.state_dict().items()}
            if log and ep % 50 == 0:
                log(f"  {self.loss} epoch {ep}: {loss.item():.4f}" + (f" (validation best {best:.4f})" if best < np.inf else ""))
            if time.perf_counter() - t0 > self.minutes * 60:
                break
        if best_state is not None:
            net.load_state_dict(best_state)
            self.val_loss_ = best
        lin = [m for m in net if isinstance(m, torch.nn.Linear)]
        self.layers_ = [(m.weight.detach().numpy().T.copy(), m.bias.detach().numpy().copy()) for m in lin]
        return self

    @staticmethod
    def _loss(torch, out, y, syms):
        if y.ndim == 3:  # rotation: 6D -> Gram-Schmidt -> L1 on the matrix, min over symmetries
            a1, a2 = out[:, :3], out[:, 3:]
            b1 = torch.nn.functional.normalize(a1, dim=1)
            b2 = torch.nn.functional.normalize(a2 - (b1 * a2).sum(1, keepdim=True) * b1, dim=1)
            R = torch.stack([b1, b2, torch.cross(b1, b2, dim=1)], dim=2)
            if syms is None:
                return (R - y).abs().sum((1, 2)).mean()
            targets = torch.einsum("nij,nsjk->nsik", y, syms)  # R_gt S
            return (R[:, None] - targets).abs().sum((2, 3)).min(1).values.mean()
        return (out - y).abs().sum(1).mean()


class KNNRegressor(DistanceKNN):
    """:class:`tracker.runtime.heads.DistanceKNN` fitted: the standardisation from
    scikit-learn's ``StandardScaler``, the training set kept in float32."""

    def fit(self, X, y):
        from sklearn.preprocessing import StandardScaler
        scaler = StandardScaler().fit(np.asarray(X, dtype=np.float64))
        self.mean_, self.scale_ = scaler.mean_, scaler.scale_
        # float32 halves what the bundle stores (the KNN keeps its training set)
        self.X_ = self._prep(X).astype(np.float32)
        self.y_ = np.asarray(y, dtype=np.float32).reshape(len(self.X_), -1)
        self.sq_ = (self.X_.astype(np.float64) ** 2).sum(1).astype(np.float32)
        return self


class BoostedTrees(Trees):
    """scikit-learn's ``HistGradientBoostingRegressor`` (L1 loss), kept as the flat arrays of
    :class:`tracker.runtime.heads.Trees`."""

    def __init__(self, max_iter=300, learning_rate=0.1, max_leaf_nodes=63, seed=0):
        self.max_iter, self.learning_rate, self.max_leaf_nodes, self.seed = max_iter, learning_rate, max_leaf_nodes, seed

    def fit(self, X, y):
        from sklearn.ensemble import HistGradientBoostingRegressor
        hgb = HistGradientBoostingRegressor(loss="absolute_error", max_iter=self.max_iter,
                                            learning_rate=self.learning_rate, max_leaf_nodes=self.max_leaf_nodes,
                                            early_stopping=False, random_state=self.seed).fit(X, y)
        return self.take_trees(hgb)

    def take_trees(self, hgb):
        """Copy a fitted ``HistGradientBoostingRegressor``'s trees (scikit-learn 1.9's layout)."""
        trees = [p.nodes for (p,) in hgb._predictors]
        if any(t["is_categorical"].any() for t in trees):
            raise ValueError("categorical splits are not supported")
        offsets = np.cumsum([0] + [len(t) for t in trees[:-1]])
        nodes = np.concatenate(trees)
        shift = np.repeat(offsets, [len(t) for t in trees])
        self.roots_ = offsets.astype(np.int64)
        self.feature_ = nodes["feature_idx"].astype(np.int64)
        self.threshold_ = nodes["num_threshold"].astype(np.float64)
        self.missing_left_ = nodes["missing_go_to_left"].astype(bool)
        self.leaf_ = nodes["is_leaf"].astype(bool)
        self.left_ = np.where(self.leaf_, np.arange(len(nodes)), nodes["left"] + shift).astype(np.int64)
        self.right_ = np.where(self.leaf_, np.arange(len(nodes)), nodes["right"] + shift).astype(np.int64)
        self.value_ = nodes["value"].astype(np.float64)
        self.depth_ = int(nodes["depth"].max())
        self.baseline_ = float(np.ravel(hgb._baseline_prediction)[0])
        self.n_features_in_ = hgb.n_features_in_
        return self
