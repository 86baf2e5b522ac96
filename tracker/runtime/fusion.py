"""Several detectors' detections fused into one list: weighted box fusion with one instance of
each object (LM-O's case; ``lab fuse-detectors`` makes such a bundle, stop 67).

Each network's candidates of an object (its peaks scoring at least the floor, after its own
class-wise NMS) go into clusters, best score first: a candidate joins the first cluster whose
first box it overlaps by IoU >= ``iou`` and that has no candidate of its network yet, else it
starts a cluster. A cluster scores the sum of its members' scores over the number of networks
(a network that misses counts 0: what one network alone sees scores less) and its box is the
score-weighted mean of its members' boxes. Networks that err differently on an object (a box
elsewhere, a box of part of it) outvote each other; their boxes of one object average.
"""
from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from tracker.core.errors import UserError
from tracker.core.geometry import iou_matrix
from tracker.runtime.estimator import Detection


@dataclass
class Fusion:
    """A manifest's ``detector.fusion``: the other networks (each a ``DetectorSpec`` dict with its
    ``file``) and how their detections join the first network's."""
    members: list[dict]
    iou: float = 0.5            # a candidate joins a cluster whose first box it overlaps this much
    floor: float = 0.05         # each network's candidates score at least this
    score_thresh: float = 0.20  # a fused detection is kept at run time from this score
    # (the first network's candidate_floor, for verified candidates, then applies to fused scores)

    @classmethod
    def from_dict(cls, d, where) -> "Fusion":
        if not isinstance(d, dict) or not isinstance(d.get("members"), list) or not d["members"] \
                or not all(isinstance(m, dict) and isinstance(m.get("file"), str) and isinstance(m.get("classes"), list)
                           for m in d["members"]):
            raise UserError(f"{where}: malformed detector fusion entry (needs 'members', each with 'file' and "
                            f"'classes'); rebuild it with 'app.py lab fuse-detectors'")
        out = cls(members=list(d["members"]), **{k: d[k] for k in cls.SETTINGS if k in d})
        if problem := out.problem():
            raise UserError(f"{where}: {problem}")
        return out

    SETTINGS = ("iou", "floor", "score_thresh")

    def problem(self, name=lambda key: f"detector fusion '{key}'") -> str | None:
        """What is wrong with the settings (None: nothing), each called by ``name(key)``."""
        for key in self.SETTINGS:
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 < v < 1:
                return f"{name(key)} must lie between 0 and 1, not {v!r}"
        return None

    def to_dict(self) -> dict:
        return {"members": self.members, "iou": self.iou, "floor": self.floor, "score_thresh": self.score_thresh,
                "method": "weighted box fusion, one instance per object (tracker/runtime/fusion.py)"}


def member_file(k: int) -> str:
    """The file of a fused detector's ``k``-th other network (k >= 1): ``detector_{k+1}.onnx``,
    its artefact role the name without ``.onnx`` (:func:`role_of`)."""
    return f"detector_{k + 1}.onnx"


def role_of(file: str) -> str | None:
    """The artefact role of a fused network's file (``detector_2.onnx`` -> ``detector_2``), None
    for a name :func:`member_file` does not make."""
    m = re.fullmatch(r"(detector_[2-9]|detector_[1-9][0-9]+)\.onnx", file)
    return m.group(1) if m else None


def member_files(entry) -> list[str]:
    """The files of a manifest ``detector`` entry's fused networks, each a name :func:`member_file`
    makes (none for one network, and none that an entry too malformed names: loading it is
    refused with the reason; a hand-edited name never reaches a path outside the bundle)."""
    f = entry.get("fusion") if isinstance(entry, dict) else None
    ms = f.get("members") if isinstance(f, dict) else None
    return [m["file"] for m in ms if isinstance(m, dict) and isinstance(m.get("file"), str)
            and role_of(m["file"]) is not None] if isinstance(ms, list) else []


def member_artefacts(entry) -> dict[str, str]:
    """The artefact roles of a detector entry's fused networks: {``detector_2``: ``detector_2.onnx``, ...}."""
    return {role_of(f): f for f in member_files(entry)}


def drop_members(manifest, folder) -> None:
    """Remove a fused detector's other networks from a bundle being rewritten (``folder``, its
    staged copy): their files and artefact roles; the caller then sets the new detector entry."""
    for f in member_files(manifest.detector or {}):
        if manifest.artefacts.get(role_of(f)) == f:
            (folder / f).unlink(missing_ok=True)
            manifest.artefacts.pop(role_of(f))


def member_problem(first, other) -> str | None:
    """Why ``other`` (a ``DetectorSpec``) cannot fuse with ``first`` (None: it can): the same
    objects and kind of box; the first network gives one instance per object."""
    if first.max_per_class != 1:
        return (f"fusion keeps one instance per object, but the first network keeps {first.max_per_class} "
                f"(max_per_class)")
    if sorted(other.classes) != sorted(first.classes) or other.boxes != first.boxes:
        return (f"it finds other objects or boxes ({sorted(other.classes)}, {other.boxes}) than the first network "
                f"({sorted(first.classes)}, {first.boxes}); fuse detectors of the same objects")
    return None


def fuse(per_network: list[list[Detection]], iou: float = 0.5) -> list[Detection]:
    """Every cluster of every object (see the module), best score first. ``per_network``: each
    network's candidates (already above its floor)."""
    n = len(per_network)
    by_obj: dict[int, list[tuple[int, Detection]]] = {}
    for k, dets in enumerate(per_network):
        for d in dets:
            by_obj.setdefault(int(d.obj_id), []).append((k, d))
    out: list[Detection] = []
    for obj, cands in by_obj.items():
        cands = sorted(cands, key=lambda c: -c[1].score)  # stable: ties keep the networks' order
        boxes = np.array([d.box for _, d in cands], float)
        ious = iou_matrix(boxes, boxes)
        clusters: list[tuple[int, set, list[int]]] = []  # (first candidate, its networks, its candidates)
        for i, (k, _) in enumerate(cands):
            for first, who, members in clusters:
                if k not in who and ious[first, i] >= iou:
                    who.add(k)
                    members.append(i)
                    break
            else:
                clusters.append((i, {k}, [i]))
        for _, _, members in clusters:
            s = np.array([cands[i][1].score for i in members], float)
            w = s / s.sum() if s.sum() > 0 else np.full(len(s), 1 / len(s))
            out.append(Detection(obj, (w[:, None] * boxes[members]).sum(0), float(s.sum() / n)))
    out.sort(key=lambda d: -d.score)
    return out


def per_object(clusters: list[Detection], k: int) -> dict[int, list[Detection]]:
    """The best ``k`` clusters of each object (``clusters`` best first)."""
    res: dict[int, list[Detection]] = {}
    for d in clusters:
        got = res.setdefault(d.obj_id, [])
        if len(got) < k:
            got.append(d)
    return res
