"""The pose head at run time: regressors on the latent code, predict-only numpy, stored as
arrays (``.npz``, read with ``allow_pickle=False``) plus a JSON description, so that loading a
bundle cannot run code. Fitting lives in :mod:`tracker.training.fit_heads` (scikit-learn, torch).

Features are camera-independent (see :func:`tracker.core.geometry.box_features`):
- rotation: ``[mu, onehot]`` -> 6D (Zhou et al.) -> R;
- centre: ``[mu, onehot, u, v, w', h']`` -> offset of the projected centre from the box
  centre in units of the box's longer side;
- distance: ``[mu, onehot, log w', log h']`` -> ``log(Tz * sqrt(w' h'))`` (the object's apparent
  size times its distance, about constant per view): k-nearest-neighbours, distance
  weighted, k and the weight of the box features chosen on validation, or an MLP where it
  does better on validation (``tracker.training.train.choose_distance``);
- distance from rotation (optional, :func:`distance_by_rotation_inputs`): ``[6D of the
  ray-frame rotation, onehot, log w', log h']`` -> the same target, gradient-boosted trees
  (:class:`Trees`) fitted on the true rotations and fed the rotation regressor's
  estimate; its log-distance is averaged with the latent one. For an unoccluded object the
  apparent size at unit distance is a function of its rotation, which the latent code
  carries only implicitly.
"""
from __future__ import annotations

import zipfile
import zlib

import numpy as np
from scipy.special import expit

from tracker.core.errors import UserError
from tracker.core.geometry import (box_features, centre_from_box_offset, matrix_from_rot6d, mean_pose, ray_rotation,
                       rot6d_from_matrix, translation_from_centre)


def _count(v, least: int = 0) -> int:
    if not isinstance(v, int) or isinstance(v, bool) or v < least:
        raise ValueError(f"expected a whole number >= {least}, not {v!r}")
    return v


def _mapping(v, what: str) -> dict:
    if not isinstance(v, dict):
        raise ValueError(f"{what} is not a mapping")
    return v


def _choice(v, options, what):
    if v not in options:
        raise ValueError(f"{what} must be one of {options}, not {v!r}")
    return v


def _silu(x):
    return x * expit(x)  # x / (1 + exp(-x)) overflows (a warning) for very negative x


class MLP:
    """A SiLU MLP evaluated with numpy: standardised input, ``layers_`` [(W, b)], SiLU between.
    ``loss`` names what it was trained for: 'l1_rotation' (output: 6D -> rotation matrix) or
    'l1'. Trained by :class:`tracker.training.fit_heads.NumpyMLP`."""

    loss = "l1"

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

    # -- storage: weights in half precision (a bundle's MLPs take half the bytes), evaluated in
    # float32; mean and scale in float32
    def to_arrays(self) -> tuple[dict, dict]:
        arrays = {"mean": np.asarray(self.mean_, np.float32), "scale": np.asarray(self.scale_, np.float32)}
        for i, (W, b) in enumerate(self.layers_):
            arrays[f"W{i}"], arrays[f"b{i}"] = W.astype(np.float16), b.astype(np.float16)
        return {"kind": "mlp", "loss": self.loss, "layers": len(self.layers_)}, arrays

    @classmethod
    def from_arrays(cls, spec: dict, arrays) -> "MLP":
        m = cls.__new__(cls)
        m.loss = _choice(spec.get("loss"), ("l1", "l1_rotation"), "an MLP's loss")
        m.mean_, m.scale_ = np.asarray(arrays["mean"], np.float32), np.asarray(arrays["scale"], np.float32)
        m.layers_ = [(np.asarray(arrays[f"W{i}"], np.float32), np.asarray(arrays[f"b{i}"], np.float32))
                     for i in range(_count(spec.get("layers"), 1))]
        width = m.mean_.shape
        if m.scale_.shape != width or len(width) != 1:
            raise ValueError("an MLP's mean and scale disagree")
        for W, b in m.layers_:
            if W.ndim != 2 or W.shape[0] != width[0] or b.shape != (W.shape[1],):
                raise ValueError("an MLP's layer shapes do not chain")
            width = (W.shape[1],)
        return m

    @property
    def n_out(self) -> int:
        return self.layers_[-1][0].shape[1]


class StackedMLP:
    """Several :class:`MLP` of the same layer shapes evaluated together: ``forward`` takes
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
        return all(isinstance(m, MLP) for m in members) and all(shapes(m) == shapes(members[0]) for m in members)

    def forward(self, X):
        h = (np.asarray(X, dtype=np.float32)[None] - self.mean_) / self.scale_
        for i, (W, b) in enumerate(self.layers_):
            h = np.matmul(h, W) + b
            if i < len(self.layers_) - 1:
                h = _silu(h)
        return h


class DistanceKNN:
    """Distance-weighted KNN on ``[mu, onehot, box]`` with the box features weighted by
    ``box_weight`` after standardisation (``mean_``, ``scale_``); predicts the log of
    Tz * sqrt(w' h'). Fitted by :class:`tracker.training.fit_heads.KNNRegressor`.

    Brute-force search in numpy, float32 like the stored training set (the same neighbours
    and weights as scikit-learn's ``KNeighborsRegressor(weights='distance', algorithm='brute')``
    up to float32 rounding; tested to 1e-5): measured on the 28 k
    training codes of models/lmo, one query took 8.4 ms through scikit-learn and 0.8 ms here,
    which is most of the per-object regression budget of the live loop."""

    def __init__(self, k=5, box_weight=3.0, n_box=2):
        self.k, self.box_weight, self.n_box = k, box_weight, n_box

    def _prep(self, X):
        Z = (np.asarray(X, dtype=np.float64) - self.mean_) / self.scale_
        Z[:, -self.n_box:] *= self.box_weight
        return Z

    def predict(self, X):
        return self.predict_ks(X, [self.k])[self.k]

    def predict_ks(self, X, ks) -> dict:
        """:meth:`predict` for several ``k`` from one neighbour search (up to the largest):
        ``{k: prediction}``, each as ``predict`` with that ``k`` gives it."""
        Z = self._prep(X).astype(np.float32)
        ks = {k: min(int(k), len(self.X_)) for k in ks}
        k_max = max(ks.values())
        out = {k: np.empty((len(Z), self.y_.shape[1]), np.float64) for k in ks}
        for a in range(0, len(Z), 256):
            z = Z[a:a + 256]
            d2 = np.maximum(self.sq_[None] - 2.0 * (z @ self.X_.T) + (z * z).sum(1)[:, None], 0.0)
            j = np.argpartition(d2, k_max - 1, axis=1)[:, :k_max]
            d2j = np.take_along_axis(d2, j, 1)
            order = np.argsort(d2j, axis=1, kind="stable")  # nearest first: the first k are the k nearest
            j, d = np.take_along_axis(j, order, 1), np.sqrt(np.take_along_axis(d2j, order, 1).astype(np.float64))
            for k, kk in ks.items():
                dk = d[:, :kk]
                exact = dk < 1e-6
                w = np.where(exact.any(1, keepdims=True), exact.astype(np.float64), 1.0 / np.maximum(dk, 1e-12))
                out[k][a:a + 256] = np.einsum("nk,nkd->nd", w, self.y_[j[:, :kk]]) / w.sum(1, keepdims=True)
        return {k: (o[:, 0] if self.y_.shape[1] == 1 else o) for k, o in out.items()}

    def to_arrays(self) -> tuple[dict, dict]:
        return ({"kind": "knn", "k": int(self.k), "box_weight": float(self.box_weight), "n_box": int(self.n_box)},
                {"mean": np.asarray(self.mean_, np.float64), "scale": np.asarray(self.scale_, np.float64),
                 "X": self.X_, "y": self.y_})

    @classmethod
    def from_arrays(cls, spec: dict, arrays) -> "DistanceKNN":
        m = cls(k=_count(spec.get("k"), 1), box_weight=float(spec.get("box_weight")), n_box=_count(spec.get("n_box")))
        m.mean_, m.scale_ = np.asarray(arrays["mean"], np.float64), np.asarray(arrays["scale"], np.float64)
        m.X_ = np.asarray(arrays["X"], np.float32)
        if m.X_.ndim != 2 or not len(m.X_) or m.mean_.shape != m.scale_.shape or m.mean_.shape != (m.X_.shape[1],):
            raise ValueError("a KNN's training set and standardisation disagree")
        m.y_ = np.asarray(arrays["y"], np.float32).reshape(len(m.X_), -1)
        m.sq_ = (m.X_.astype(np.float64) ** 2).sum(1).astype(np.float32)
        return m


class Trees:
    """Gradient-boosted regression trees kept as flat arrays and predicted with vectorised
    numpy (scikit-learn's ``HistGradientBoostingRegressor``'s own predict costs 20-40 ms per call
    whatever the batch, over the per-object budget; this walks every tree at once, one level per
    step). Numerical features only; NaN follows the trees' missing-value side. Fitted by
    :class:`tracker.training.fit_heads.BoostedTrees`."""

    _ARRAYS = {"roots": ("roots_", np.int64), "feature": ("feature_", np.int64), "threshold": ("threshold_", np.float64),
               "missing_left": ("missing_left_", bool), "leaf": ("leaf_", bool), "left": ("left_", np.int64),
               "right": ("right_", np.int64), "value": ("value_", np.float64)}

    def predict(self, X):
        X = np.asarray(X, dtype=np.float64)
        return walk_trees(self, X, np.broadcast_to(self.roots_, (len(X), len(self.roots_)))) + self.baseline_

    def to_arrays(self) -> tuple[dict, dict]:
        return ({"kind": "trees", "depth": int(self.depth_), "baseline": float(self.baseline_),
                 "n_features": int(self.n_features_in_)},
                {k: np.asarray(getattr(self, a), t) for k, (a, t) in self._ARRAYS.items()})

    @classmethod
    def from_arrays(cls, spec: dict, arrays) -> "Trees":
        m = cls.__new__(cls)
        for k, (a, t) in cls._ARRAYS.items():
            setattr(m, a, np.asarray(arrays[k], t))
        n = len(m.feature_)
        if not all(len(getattr(m, a)) == n for a in ("threshold_", "missing_left_", "leaf_", "left_", "right_", "value_")) \
                or any(((i < 0) | (i >= n)).any() for i in (m.roots_, m.left_, m.right_)):
            raise ValueError("the trees' node arrays disagree")
        inner = np.nonzero(~m.leaf_)[0]  # children come after their node: every walk ends
        if (m.left_[inner] <= inner).any() or (m.right_[inner] <= inner).any():
            raise ValueError("the trees' child links do not point forward")
        m.depth_, m.baseline_ = _count(spec.get("depth")), float(spec.get("baseline"))
        m.n_features_in_ = _count(spec.get("n_features"))
        if (m.feature_[~m.leaf_] >= m.n_features_in_).any():
            raise ValueError("a tree splits on a feature it does not have")
        return m


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
    """The forests of several :class:`Trees` in one set of flat arrays, so that M
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


class Codebook:
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

    def to_arrays(self) -> dict:
        return {f"{o}.{k}": v for o, arrs in self.codes_.items() for k, v in zip(("codes", "R", "tz_size"), arrs)}

    @classmethod
    def from_arrays(cls, arrays) -> "Codebook":
        cb = cls()
        ids = sorted({int(k.split(".")[0]) for k in arrays.keys()})
        cb.codes_ = {o: tuple(np.asarray(arrays[f"{o}.{k}"], np.float32) for k in ("codes", "R", "tz_size")) for o in ids}
        return cb

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
    rotations relative to the viewing ray (allocentric, :func:`tracker.core.geometry.ray_rotation`),
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
        return R, translation_from_centre(centre, tz, K)


class HeadEnsemble(PoseHead):
    """Several head sets fitted on the same frozen encoder (``app.py lab join-heads``), their poses
    averaged by :func:`tracker.core.geometry.mean_pose`. A symmetric object's estimates may differ by
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

    def stacked(self):
        """The members' regressors stacked (:class:`StackedMLP`, :class:`StackedTrees`) where
        they are alike (MLPs of one shape, trees in all or none), else None."""
        if not hasattr(self, "_stacked"):
            hs = self.members
            trees = [getattr(h, "distance_by_rotation", None) for h in hs]
            ok = (all(StackedMLP.stackable([getattr(h, k, None) for h in hs]) for k in ("rotation", "centre", "distance"))
                  and all(h.rotation.loss == "l1_rotation" for h in hs)
                  and (all(t is None for t in trees) or all(isinstance(t, Trees) for t in trees)))
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


# --------------------------------------------------------------------------- storage

HEAD_FORMAT = 1
_REGRESSORS = {"mlp": MLP, "knn": DistanceKNN, "trees": Trees}
_SLOTS = ("rotation", "centre", "distance", "distance_by_rotation")


def _head_spec(h: PoseHead, prefix: str, arrays: dict) -> dict:
    spec = {"obj_ids": list(h.obj_ids), "rotation_frame": h.rotation_frame}
    for slot in _SLOTS:
        r = getattr(h, slot, None)
        if r is None:
            spec[slot] = None
            continue
        if not hasattr(r, "to_arrays"):
            raise TypeError(f"a {type(r).__name__} cannot be stored in a bundle")
        spec[slot], arrs = r.to_arrays()
        spec[slot]["arrays"] = f"{prefix}{slot}"
        arrays.update({f"{prefix}{slot}.{k}": v for k, v in arrs.items()})
    return spec


def head_to_arrays(head: PoseHead) -> tuple[dict, dict]:
    """(JSON-able description, {name: array}) of a pose head or head ensemble (no codebook)."""
    arrays: dict = {}
    members = head.members if isinstance(head, HeadEnsemble) else [head]
    spec = {"format": HEAD_FORMAT, "kind": "ensemble" if isinstance(head, HeadEnsemble) else "head",
            "members": [_head_spec(h, f"m{i}.", arrays) for i, h in enumerate(members)]}
    if isinstance(head, HeadEnsemble):
        spec["symmetries"] = {str(o): np.asarray(S, np.float64).reshape(-1, 9).tolist() for o, S in head.symmetries.items()}
    return spec, arrays


def _sub(arrays, name: str) -> dict:
    n = len(name) + 1
    return {k[n:]: arrays[k] for k in arrays.keys() if k.startswith(name + ".")}


def head_from_arrays(spec: dict, arrays) -> PoseHead:
    """The inverse of :func:`head_to_arrays`; ``arrays``: a mapping (an open ``np.load``)."""
    if not isinstance(spec, dict) or spec.get("format") != HEAD_FORMAT:
        raise ValueError(f"not a pose head description of format {HEAD_FORMAT}")
    members = spec.get("members")
    if not isinstance(members, list):
        raise ValueError("'members' is not a list")
    heads = []
    for m in members:
        m = _mapping(m, "a member")
        parts = {}
        for slot in _SLOTS:
            r = m.get(slot)
            if r is None:
                parts[slot] = None
                continue
            r = _mapping(r, f"the {slot} regressor")
            kind = _choice(r.get("kind"), tuple(_REGRESSORS), f"the {slot} regressor's kind")
            parts[slot] = _REGRESSORS[kind].from_arrays(r, _sub(arrays, str(r.get("arrays"))))
        if parts["rotation"] is None or parts["centre"] is None or parts["distance"] is None:
            raise ValueError("a head needs rotation, centre and distance regressors")
        for slot, n_out in (("rotation", 6), ("centre", 2)):
            if not isinstance(parts[slot], MLP) or parts[slot].n_out != n_out:
                raise ValueError(f"the {slot} regressor must be an MLP with {n_out} outputs")
        heads.append(PoseHead([int(o) for o in m["obj_ids"]], parts["rotation"], parts["centre"], parts["distance"],
                              rotation_frame=m.get("rotation_frame"), distance_by_rotation=parts["distance_by_rotation"]))
    if not heads:
        raise ValueError("no heads")
    if spec.get("kind") == "ensemble":
        syms = {int(o): np.asarray(S, np.float64).reshape(-1, 3, 3)
                for o, S in _mapping(spec.get("symmetries") or {}, "'symmetries'").items()}
        return HeadEnsemble(heads, syms)
    if spec.get("kind") != "head" or len(heads) != 1:
        raise ValueError("a 'head' has exactly one member")
    return heads[0]


def save_head(head: PoseHead, json_path, npz_path) -> None:
    """Write a pose head as ``json_path`` (its description) + ``npz_path`` (its arrays)."""
    import json
    spec, arrays = head_to_arrays(head)
    with open(npz_path, "wb") as f:
        np.savez_compressed(f, **arrays)
    with open(json_path, "w") as f:
        json.dump(spec, f, indent=1)


def save_codebook(codebook: Codebook, npz_path) -> None:
    with open(npz_path, "wb") as f:
        np.savez_compressed(f, **codebook.to_arrays())


def load_head(json_path, npz_path) -> PoseHead:
    """Read a pose head (numpy with ``allow_pickle=False``: no code runs). Raises ValueError
    (or OSError) on a malformed pair."""
    import json
    with open(json_path) as f:
        spec = json.load(f)
    with np.load(npz_path, allow_pickle=False) as arrays:
        return head_from_arrays(spec, arrays)


def load_codebook(npz_path) -> Codebook:
    with np.load(npz_path, allow_pickle=False) as arrays:
        return Codebook.from_arrays(arrays)


# what reading a malformed pose head or codebook can raise (numpy, zipfile, zlib, JSON)
_UNREADABLE = (ValueError, KeyError, TypeError, OSError, AttributeError, IndexError, EOFError, zipfile.BadZipFile,
               zlib.error)


def load_bundle_head(bundle):
    """A bundle's pose head (:class:`tracker.core.bundle.Bundle`, verified when opened): JSON +
    arrays, no pickles; a one-line error for a malformed one."""
    spec, arrays = bundle.path("pose_head"), bundle.path("pose_head_arrays")
    try:
        return load_head(spec, arrays)
    except _UNREADABLE as e:
        raise UserError(f"{spec}: unreadable pose head ({e.__class__.__name__}: {str(e)[:100]}); the bundle "
                        f"was built broken: rebuild it") from None


def load_bundle_codebook(bundle) -> Codebook:
    """A bundle's AAE codebook (``eval --mode aae``); a one-line error for a malformed one."""
    path = bundle.path("codebook")
    try:
        return load_codebook(path)
    except _UNREADABLE as e:
        raise UserError(f"{path}: unreadable codebook ({e.__class__.__name__}: {str(e)[:100]}); the bundle "
                        f"was built broken: rebuild it") from None
