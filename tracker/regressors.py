"""Pose regressors on the latent code, with the scikit-learn API and numpy-only ``predict``
(so a bundle runs without torch). Training of :class:`NumpyMLP` imports torch lazily.

Features are camera-independent (see :func:`tracker.geometry.box_features`):
- rotation: ``[mu, onehot]`` -> 6D (Zhou et al.) -> R;
- centre: ``[mu, onehot, u, v, w', h']`` -> offset of the projected centre from the box
  centre in units of the box's longer side;
- distance: ``[mu, onehot, log w', log h']`` -> ``log(Tz * sqrt(w' h'))`` (the object's apparent
  size times its distance, about constant per view): k-nearest-neighbours, distance
  weighted, k and the weight of the box features chosen on validation, or an MLP where it
  does better on validation (``tracker.train.choose_distance``);
- distance from rotation (optional, :func:`distance_by_rotation_inputs`): ``[6D of the
  ray-frame rotation, onehot, log w', log h']`` -> the same target, gradient-boosted trees
  (:class:`BoostedTrees`) fitted on the true rotations and fed the rotation regressor's
  estimate; its log-distance is averaged with the latent one. For an unoccluded object the
  apparent size at unit distance is a function of its rotation, which the latent code
  carries only implicitly.
"""
from __future__ import annotations

import numpy as np
from scipy.special import expit
from sklearn.base import BaseEstimator, RegressorMixin
from sklearn.preprocessing import StandardScaler

from .errors import UserError
from .geometry import (box_features, centre_from_box_offset, matrix_from_rot6d, mean_pose, ray_rotation,
                       rot6d_from_matrix, translation_from_centre)


def _silu(x):
    return x * expit(x)  # x / (1 + exp(-x)) overflows (a warning) for very negative x


class NumpyMLP(BaseEstimator, RegressorMixin):
    """A SiLU MLP trained with torch, evaluated with numpy. ``loss``: 'l1_rotation' (input
    -> 6D, L1 between rotation matrices, minimum over the object's symmetries) or 'l1'."""

    def __init__(self, hidden=(256, 256), loss="l1", epochs=300, lr=3e-3, batch=1024, weight_decay=1e-4,
                 seed=0, minutes=5.0):
        self.hidden, self.loss, self.epochs, self.lr, self.batch = hidden, loss, epochs, lr, batch
        self.weight_decay, self.seed, self.minutes = weight_decay, seed, minutes

    # -- numpy inference
    def _forward(self, X):
        h = (np.asarray(X, dtype=np.float32) - self.mean_) / self.scale_
        for i, (W, b) in enumerate(self.layers_):
            h = h @ W + b
            if i < len(self.layers_) - 1:
                h = _silu(h)
        return h

    def predict(self, X):
        out = self._forward(X)
        return matrix_from_rot6d(out) if self.loss == "l1_rotation" else out

    # -- storage: weights pickled in half precision (a bundle's MLPs take half the bytes, and
    # float32 weights hardly compress), evaluated in float32 as before
    def __getstate__(self):
        state = dict(super().__getstate__())
        if "layers_" in state:
            state["layers_"] = [(W.astype(np.float16), b.astype(np.float16)) for W, b in state["layers_"]]
        return state

    def __setstate__(self, state):
        state = dict(state)
        if "layers_" in state:
            state["layers_"] = [(np.asarray(W, np.float32), np.asarray(b, np.float32)) for W, b in state["layers_"]]
        super().__setstate__(state)

    # -- training (torch)
    def fit(self, X, Y, sym_R=None, X_val=None, Y_val=None, sym_val=None, log=None):
        """``Y``: (N, 3, 3) rotations for 'l1_rotation', else (N, D). ``sym_R``: (N, S, 3, 3)
        symmetry rotations per sample (identity first) for the rotation loss. With a
        validation set, the weights of the epoch with the lowest validation loss are kept
        (checked every 5 epochs): the latent codes are few and an MLP overfits them."""
        import time

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


class StackedMLP:
    """Several :class:`NumpyMLP` of the same layer shapes evaluated together: ``forward`` takes
    one (N, D) input for all and gives (M, N, out), the same arithmetic as each one's
    ``_forward`` in batched matrix products."""

    def __init__(self, members):
        self.mean_ = np.stack([m.mean_ for m in members])[:, None]
        self.scale_ = np.stack([m.scale_ for m in members])[:, None]
        self.layers_ = [(np.stack([m.layers_[i][0] for m in members]), np.stack([m.layers_[i][1] for m in members])[:, None])
                        for i in range(len(members[0].layers_))]

    @staticmethod
    def stackable(members) -> bool:
        shapes = lambda m: [(W.shape, b.shape) for W, b in m.layers_] + [np.shape(m.mean_), np.shape(m.scale_)]
        return all(isinstance(m, NumpyMLP) for m in members) and all(shapes(m) == shapes(members[0]) for m in members)

    def forward(self, X):
        h = (np.asarray(X, dtype=np.float32)[None] - self.mean_) / self.scale_
        for i, (W, b) in enumerate(self.layers_):
            h = np.matmul(h, W) + b
            if i < len(self.layers_) - 1:
                h = _silu(h)
        return h


class DistanceKNN(BaseEstimator, RegressorMixin):
    """Distance-weighted KNN on ``[mu, onehot, box]`` with the box features weighted by
    ``box_weight`` after standardisation; predicts the log of Tz * sqrt(w' h').

    Brute-force search in numpy, float32 like the stored training set (the same neighbours
    and weights as scikit-learn's ``KNeighborsRegressor(weights='distance', algorithm='brute')``
    up to float32 rounding; tested to 1e-5): measured on the 28 k
    training codes of models/lmo, one query took 8.4 ms through scikit-learn and 0.8 ms here,
    which is most of the per-object regression budget of the live loop."""

    def __init__(self, k=5, box_weight=3.0, n_box=2):
        self.k, self.box_weight, self.n_box = k, box_weight, n_box

    def _prep(self, X):
        Z = self.scaler_.transform(np.asarray(X, dtype=np.float64))
        Z[:, -self.n_box:] *= self.box_weight
        return Z

    def fit(self, X, y):
        self.scaler_ = StandardScaler().fit(np.asarray(X, dtype=np.float64))
        # float32 halves what the bundle stores (the KNN keeps its training set)
        self.X_ = self._prep(X).astype(np.float32)
        self.y_ = np.asarray(y, dtype=np.float32).reshape(len(self.X_), -1)
        self.sq_ = (self.X_.astype(np.float64) ** 2).sum(1).astype(np.float32)
        return self

    def __setstate__(self, state):
        knn = state.pop("knn_", None)  # bundles pickled with a scikit-learn KNeighborsRegressor inside
        self.__dict__.update(state)
        if knn is not None:
            self.X_ = np.asarray(knn._fit_X, dtype=np.float32)
            self.y_ = np.asarray(knn._y, dtype=np.float32).reshape(len(self.X_), -1)
            self.sq_ = (self.X_.astype(np.float64) ** 2).sum(1).astype(np.float32)

    def predict(self, X):
        Z = self._prep(X).astype(np.float32)
        k = min(self.k, len(self.X_))
        out = np.empty((len(Z), self.y_.shape[1]), np.float64)
        for a in range(0, len(Z), 256):
            z = Z[a:a + 256]
            d2 = np.maximum(self.sq_[None] - 2.0 * (z @ self.X_.T) + (z * z).sum(1)[:, None], 0.0)
            j = np.argpartition(d2, k - 1, axis=1)[:, :k]
            d = np.sqrt(np.take_along_axis(d2, j, 1).astype(np.float64))
            exact = d < 1e-6
            w = np.where(exact.any(1, keepdims=True), exact.astype(np.float64), 1.0 / np.maximum(d, 1e-12))
            out[a:a + 256] = np.einsum("nk,nkd->nd", w, self.y_[j]) / w.sum(1, keepdims=True)
        return out[:, 0] if self.y_.shape[1] == 1 else out


class BoostedTrees(BaseEstimator, RegressorMixin):
    """scikit-learn's ``HistGradientBoostingRegressor`` (L1 loss), kept as flat arrays and
    predicted with vectorised numpy: the library's own predict costs 20-40 ms per call whatever
    the batch (measured here, 300 trees), over the per-object budget; this walks every tree at
    once, one level per step. Numerical features only; NaN follows the trees' missing-value side."""

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

    def predict(self, X):
        X = np.asarray(X, dtype=np.float64)
        return walk_trees(self, X, np.broadcast_to(self.roots_, (len(X), len(self.roots_)))) + self.baseline_


def walk_trees(forest, X, roots) -> np.ndarray:
    """Sum over trees of the leaf values each row of ``X`` reaches from its row of ``roots``
    (node indices into ``forest``'s flat arrays): every tree at once, one level per step, each
    step only over the (row, tree) pairs not yet at a leaf (most trees end well above the
    deepest: measured, 40 rows x 1,500 trees, 1.4 against 3.3 ms walking all to the bottom)."""
    node = np.array(roots, dtype=np.int64)
    flat = node.reshape(-1)
    rows = np.repeat(np.arange(len(X)), node.shape[1])
    active = np.nonzero(~forest.leaf_[flat])[0]
    while active.size:
        nd = flat[active]
        x = X[rows[active], forest.feature_[nd]]
        left = (x <= forest.threshold_[nd]) | (np.isnan(x) & forest.missing_left_[nd])
        nd = np.where(left, forest.left_[nd], forest.right_[nd])
        flat[active] = nd
        active = active[~forest.leaf_[nd]]
    return forest.value_[flat].reshape(node.shape).sum(axis=1)


class StackedTrees:
    """The forests of several :class:`BoostedTrees` in one set of flat arrays, so that M
    members' trees are walked for all their inputs in one pass: ``predict`` takes (M, N, F)
    and gives (M, N), member m's trees on ``X[m]``. Forests with fewer trees are padded with a
    leaf of value 0."""

    def __init__(self, members):
        T = max(len(f.roots_) for f in members)
        offsets = np.cumsum([0] + [len(f.feature_) for f in members])
        pad = int(offsets[-1])  # one extra node: a leaf worth 0
        cat = lambda name, extra: np.concatenate([getattr(f, name) for f in members] + [np.array([extra])])
        self.feature_, self.threshold_ = cat("feature_", 0), cat("threshold_", 0.0)
        self.missing_left_, self.leaf_, self.value_ = cat("missing_left_", True), cat("leaf_", True), cat("value_", 0.0)
        self.left_ = np.concatenate([f.left_ + o for f, o in zip(members, offsets)] + [np.array([pad])])
        self.right_ = np.concatenate([f.right_ + o for f, o in zip(members, offsets)] + [np.array([pad])])
        self.roots_ = np.full((len(members), T), pad, np.int64)
        for m, (f, o) in enumerate(zip(members, offsets)):
            self.roots_[m, :len(f.roots_)] = f.roots_ + o
        self.depth_ = max(f.depth_ for f in members)
        self.baseline_ = np.array([f.baseline_ for f in members])

    def predict(self, X):
        X = np.asarray(X, dtype=np.float64)
        M, N = X.shape[:2]
        member = np.repeat(np.arange(M), N)
        out = walk_trees(self, X.reshape(M * N, -1), self.roots_[member]) + self.baseline_[member]
        return out.reshape(M, N)


class Codebook(BaseEstimator):
    """AAE's lookup table (Sundermeyer et al.): L2-normalised latent codes of training views
    per object; cosine nearest neighbour gives the rotation, and the view's distance times
    its box size over the query's box size gives Tz."""

    def fit(self, mu, obj_id, R, tz_size):
        self.codes_ = {}
        for o in np.unique(obj_id):
            m = obj_id == o
            c = mu[m] / (np.linalg.norm(mu[m], axis=1, keepdims=True) + 1e-9)
            self.codes_[int(o)] = (c.astype(np.float32), R[m].astype(np.float32), tz_size[m].astype(np.float32))
        return self

    def predict(self, mu, obj_id):
        """(R (N, 3, 3), Tz * size of the nearest view (N,))."""
        Rs = np.zeros((len(mu), 3, 3))
        ts = np.zeros(len(mu))
        q = mu / (np.linalg.norm(mu, axis=1, keepdims=True) + 1e-9)
        for o in np.unique(obj_id):
            m = obj_id == o
            codes, R, tzs = self.codes_[int(o)]
            j = np.argmax(q[m] @ codes.T, axis=1)
            Rs[m], ts[m] = R[j], tzs[j]
        return Rs, ts


# --------------------------------------------------------------------------- features


def onehot(obj_idx: np.ndarray, n: int) -> np.ndarray:
    return np.eye(n, dtype=np.float32)[np.asarray(obj_idx, dtype=int)]


def rotation_inputs(mu, obj_idx, n_obj) -> np.ndarray:
    return np.hstack([mu, onehot(obj_idx, n_obj)]).astype(np.float32)


def centre_inputs(mu, obj_idx, n_obj, boxes, K) -> np.ndarray:
    return np.hstack([rotation_inputs(mu, obj_idx, n_obj), box_features(boxes, K)]).astype(np.float32)


def distance_inputs(mu, obj_idx, n_obj, boxes, K) -> np.ndarray:
    bf = box_features(boxes, K)
    return np.hstack([rotation_inputs(mu, obj_idx, n_obj), np.log(bf[:, 2:4])]).astype(np.float32)


def distance_by_rotation_inputs(R_ray, obj_idx, n_obj, boxes, K) -> np.ndarray:
    """``[6D of the ray-frame rotation, onehot, log w', log h']``."""
    R_ray = np.asarray(R_ray, dtype=np.float64).reshape(-1, 3, 3)
    bf = box_features(boxes, K)
    return np.hstack([rot6d_from_matrix(R_ray).reshape(len(R_ray), 6), onehot(obj_idx, n_obj),
                      np.log(bf[:, 2:4])]).astype(np.float32)


def apparent_size(boxes, K) -> np.ndarray:
    """sqrt(w' h'): the box's size over the focal length (camera-independent)."""
    bf = box_features(boxes, K)
    return np.sqrt(bf[:, 2] * bf[:, 3])


# --------------------------------------------------------------------------- the pose head


# the distance-from-rotation trees' share of the log distance (the rest: the latent MLP's)
TREES_WEIGHT = 0.5


def trees_used(trees_weight) -> bool:
    """Whether any crop gives the trees a share (else they need not run)."""
    return bool(np.any(np.asarray(trees_weight) > 0))


def mix_log_distance(latent, trees, trees_weight):
    """The log distance: the trees' share ``trees_weight`` (one, or one per crop: the last axis)
    of theirs, the rest the latent MLP's."""
    w = np.asarray(trees_weight, np.float64)
    return (1 - w) * latent + w * trees


class PoseHead:
    """Latent code + box -> pose, by regression (the thesis) or by the AAE codebook.

    ``rotation_frame``: 'ray' when the rotation regressor and the codebook were trained on
    rotations relative to the viewing ray (allocentric, :func:`tracker.geometry.ray_rotation`),
    turned back into the camera frame through the estimated centre; 'camera' (bundles made
    before it existed) when they predict the camera-frame rotation directly."""

    rotation_frame = "camera"  # the defaults of heads pickled without the attributes
    distance_by_rotation = None

    def __init__(self, obj_ids, rotation, centre, distance, codebook=None, rotation_frame="ray",
                 distance_by_rotation=None):
        self.obj_ids = [int(o) for o in obj_ids]
        self.rotation, self.centre, self.distance, self.codebook = rotation, centre, distance, codebook
        if rotation_frame not in ("ray", "camera"):
            raise ValueError(f"rotation_frame must be 'ray' or 'camera', not {rotation_frame!r}")
        if distance_by_rotation is not None and rotation_frame != "ray":
            raise ValueError("distance_by_rotation needs ray-frame rotations")
        self.rotation_frame = rotation_frame
        self.distance_by_rotation = distance_by_rotation

    def index(self, obj_ids) -> np.ndarray:
        lut = {o: i for i, o in enumerate(self.obj_ids)}
        try:
            return np.array([lut[int(o)] for o in obj_ids], dtype=int)
        except KeyError as e:
            raise UserError(f"object {e.args[0]} is not in this bundle (has {self.obj_ids})") from None

    def predict(self, mu, obj_ids, boxes, K, mode: str = "regression", trees_weight: float = TREES_WEIGHT):
        """Poses (R (N, 3, 3), t (N, 3) mm) for latent codes ``mu`` of crops cut from ``boxes``;
        ``trees_weight`` (one, or one per crop): the distance-from-rotation trees' share of the log
        distance, the latent MLP's the rest (0: the trees are not run)."""
        idx = self.index(obj_ids)
        n = len(self.obj_ids)
        boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
        if mode == "aae":
            R, tz_size = self.codebook.predict(mu, np.asarray(obj_ids))
            offset = np.zeros((len(mu), 2))  # the box centre stands for the object's centre
            return self.assemble(R, offset, tz_size, boxes, K)
        R = self.rotation.predict(rotation_inputs(mu, idx, n))
        offset = self.centre.predict(centre_inputs(mu, idx, n, boxes, K))
        log_tz_size = np.ravel(self.distance.predict(distance_inputs(mu, idx, n, boxes, K)))  # KNN: (N,), MLP: (N, 1)
        if self.distance_by_rotation is not None and trees_used(trees_weight):
            by_r = np.ravel(self.distance_by_rotation.predict(distance_by_rotation_inputs(R, idx, n, boxes, K)))
            log_tz_size = mix_log_distance(log_tz_size, by_r, trees_weight)
        return self.assemble(R, offset, np.exp(log_tz_size), boxes, K)

    def assemble(self, R, offset, tz_size, boxes, K):
        """The pose from what the regressors give: the rotation (in the ray frame where the head
        has one), the centre's offset from the box centre, and distance x apparent size."""
        tz = tz_size / apparent_size(boxes, K)
        centre = centre_from_box_offset(boxes, offset)
        K = np.asarray(K, dtype=np.float64)
        if self.rotation_frame == "ray":
            R = ray_rotation(centre, K) @ R
        if K.ndim == 2:
            t = translation_from_centre(centre, tz, K)
        else:
            t = np.stack([translation_from_centre(c, z, k) for c, z, k in zip(centre, tz, K)])
        return R, t


class HeadEnsemble(PoseHead):
    """Several head sets fitted on the same frozen encoder (``app.py join-heads``), their poses
    averaged by :func:`tracker.geometry.mean_pose`. A symmetric object's estimates may differ by
    one of its symmetries: each member's rotation is first turned by the symmetry that brings it
    closest to the first member's. The AAE mode is the first member's with the bundle's codebook.
    ``symmetries``: {obj_id: (S, 3, 3) model-frame symmetry rotations, identity first}."""

    def __init__(self, members, symmetries: dict):
        members = [m for h in members for m in (h.members if isinstance(h, HeadEnsemble) else [h])]
        if not members:
            raise ValueError("an ensemble needs at least one head")
        for h in members:
            if h.obj_ids != members[0].obj_ids or h.rotation_frame != members[0].rotation_frame:
                raise UserError(f"heads for objects {h.obj_ids} ({h.rotation_frame} frame) cannot be averaged with "
                                f"heads for {members[0].obj_ids} ({members[0].rotation_frame} frame)")
        self.members = members
        self.obj_ids = list(members[0].obj_ids)
        self.rotation_frame = members[0].rotation_frame
        self.rotation = self.centre = self.distance = self.codebook = None
        self.symmetries = {int(o): np.asarray(symmetries.get(int(o), np.eye(3)[None]), np.float64).reshape(-1, 3, 3)
                           for o in self.obj_ids}

    def __getstate__(self):
        return {k: v for k, v in self.__dict__.items() if k != "_stacked"}  # rebuilt on first use

    def stacked(self):
        """The members' regressors stacked (:class:`StackedMLP`, :class:`StackedTrees`) where
        they are alike (MLPs of one shape, trees in all or none), else None."""
        if not hasattr(self, "_stacked"):
            hs = self.members
            trees = [getattr(h, "distance_by_rotation", None) for h in hs]
            ok = (all(StackedMLP.stackable([getattr(h, k, None) for h in hs]) for k in ("rotation", "centre", "distance"))
                  and all(h.rotation.loss == "l1_rotation" for h in hs)
                  and (all(t is None for t in trees) or all(isinstance(t, BoostedTrees) for t in trees)))
            self._stacked = None if not ok else {
                **{k: StackedMLP([getattr(h, k) for h in hs]) for k in ("rotation", "centre", "distance")},
                "trees": None if trees[0] is None else StackedTrees(trees)}
        return self._stacked

    def member_poses(self, mu, obj_ids, boxes, K, trees_weight: float = TREES_WEIGHT):
        """Every member's poses, (M, N, 3, 3) and (M, N, 3): stacked where the members allow it
        (measured, seven members, 8 crops,
        interleaved: 8.2-11.3 against 11.7-15.8 ms), else one member after another."""
        st = self.stacked()
        if st is None:
            Rs, ts = zip(*(h.predict(mu, obj_ids, boxes, K, trees_weight=trees_weight) for h in self.members))
            return np.stack(Rs), np.stack(ts)
        idx, n, M, N = self.index(obj_ids), len(self.obj_ids), len(self.members), len(mu)
        boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
        R = matrix_from_rot6d(st["rotation"].forward(rotation_inputs(mu, idx, n)))  # (M, N, 3, 3)
        offset = st["centre"].forward(centre_inputs(mu, idx, n, boxes, K))
        log_tz_size = st["distance"].forward(distance_inputs(mu, idx, n, boxes, K))[..., 0]
        K = np.asarray(K, dtype=np.float64)
        all_boxes, all_K = np.tile(boxes, (M, 1)), (K if K.ndim == 2 else np.tile(K, (M, 1, 1)))
        if st["trees"] is not None and trees_used(trees_weight):
            X = distance_by_rotation_inputs(R.reshape(-1, 3, 3), np.tile(idx, M), n, all_boxes, all_K)
            log_tz_size = mix_log_distance(log_tz_size, st["trees"].predict(X.reshape(M, N, -1)), trees_weight)
        R, t = self.assemble(R.reshape(-1, 3, 3), offset.reshape(-1, 2), np.exp(log_tz_size).ravel(), all_boxes, all_K)
        return R.reshape(M, N, 3, 3), t.reshape(M, N, 3)

    def predict(self, mu, obj_ids, boxes, K, mode: str = "regression", trees_weight: float = TREES_WEIGHT):
        if mode == "aae":
            first = self.members[0]
            first.codebook = self.codebook
            return first.predict(mu, obj_ids, boxes, K, mode=mode)
        Rs, ts = self.member_poses(mu, obj_ids, boxes, K, trees_weight=trees_weight)
        for n, o in enumerate(obj_ids):
            S = self.symmetries[int(o)]
            if len(S) > 1:  # the symmetry of each member's estimate nearest the first member's
                turned = Rs[1:, n, None] @ S[None]  # (M - 1, S, 3, 3)
                best = np.argmax(np.einsum("ij,msij->ms", Rs[0, n], turned), axis=1)
                Rs[1:, n] = turned[np.arange(len(best)), best]
        return mean_pose(Rs, ts)
