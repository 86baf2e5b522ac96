"""A bundle's manifest as one typed object, with one reader (:meth:`Manifest.from_dict`) and one
writer (:meth:`Manifest.to_dict`, hashed into ``manifest.json`` by
:func:`tracker.core.bundle.write_manifest`).

The fields that code reads are typed and checked when a manifest is read; the records of how
the bundle was made (``training``, ``validation_synthetic``, ``heads``' provenance, the detector's
training) are kept as the mappings they are. Keys this version does not know are kept in
``extra`` and written back unchanged. ``format`` is the schema version: 2 is the first without
pickles (the pose head as JSON + ``.npz``); format 1 bundles are refused.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from tracker.core.bop import positive_number
from tracker.core.errors import UserError

FORMAT = 2
MANIFEST = "manifest.json"


@dataclass
class ObjectEntry:
    id: int
    mesh: str  # relative to the bundle
    diameter: float  # mm
    name: str = ""
    symmetries_discrete: list = field(default_factory=list)  # flattened 4x4 (BOP)
    symmetries_continuous: list = field(default_factory=list)
    overlay_mesh: str | None = None  # a light mesh for the overlay, relative to the bundle
    extra: dict = field(default_factory=dict)  # keys this version does not read, kept as they are

    def to_dict(self) -> dict:
        d = {**self.extra, "id": self.id, "name": self.name, "mesh": self.mesh, "diameter": self.diameter,
             "symmetries_discrete": self.symmetries_discrete, "symmetries_continuous": self.symmetries_continuous}
        if self.overlay_mesh is not None:
            d["overlay_mesh"] = self.overlay_mesh
        return d


@dataclass
class Manifest:
    name: str
    method: str  # dalsr | cvml | cvam
    input_size: int  # crop side in pixels
    latent_size: int
    objects: list[ObjectEntry]
    artefacts: dict[str, str]  # role -> file relative to the bundle (encoder, pose_head, ...)
    encoder: str = "plain"
    pose_prior: str = "sphere"
    training_camera: dict | None = None
    detector: dict | None = None  # tracker.runtime.detector.DetectorSpec's fields + its training record
    heads: dict = field(default_factory=dict)  # how the pose head was made; trees_weight is read at run time
    training: dict = field(default_factory=dict)
    validation_synthetic: dict = field(default_factory=dict)
    command: str | None = None
    created: str | None = None
    extra: dict = field(default_factory=dict)  # keys this version does not read, kept as they are
    files: dict[str, dict] = field(default_factory=dict)  # path -> {sha256, bytes}; derived by the writer
    format: int = FORMAT

    # ------------------------------------------------------------------ reading and writing

    @classmethod
    def from_dict(cls, d: dict, where) -> "Manifest":
        """The one reader: a manifest's JSON object, checked; a one-line error names ``where``."""
        def bad(what):
            raise UserError(f"{where}: malformed manifest ({what}); rebuild the bundle")
        if not isinstance(d, dict):
            bad("not a JSON object")
        fmt = d.get("format")
        if fmt != FORMAT:
            if fmt == 1:
                raise UserError(f"{where}: a bundle of format 1, whose pose head is a pickle (loading it could run "
                                f"code); this version reads format {FORMAT} only: rebuild the bundle")
            bad(f"format {fmt!r}, this version reads {FORMAT}")
        files = d.get("files")
        if not isinstance(files, dict) or not all(isinstance(m, dict) for m in files.values()):
            bad("no 'files' mapping")
        objs = d.get("objects")
        if not isinstance(objs, list) or not objs:
            bad("no 'objects' list")
        objects = []
        for o in objs:
            if not isinstance(o, dict):
                bad("an object entry is not a mapping")
            for key, kind in (("id", int), ("mesh", str), ("diameter", (int, float))):
                if not isinstance(o.get(key), kind) or isinstance(o.get(key), bool):
                    bad(f"object {o.get('id', '?')}: '{key}' missing or not a {getattr(kind, '__name__', 'number')}")
            if not positive_number(o["diameter"]):
                bad(f"object {o['id']}: 'diameter' must be positive (mm), not {o['diameter']}")
            known = {f.name for f in dataclasses.fields(ObjectEntry)} - {"extra"}
            objects.append(ObjectEntry(**{k: v for k, v in o.items() if k in known},
                                       extra={k: v for k, v in o.items() if k not in known}))
        for key in ("input_size", "latent_size"):
            v = d.get(key)
            if not isinstance(v, int) or isinstance(v, bool) or v <= 0:
                bad(f"'{key}' missing or not a positive integer")
        for key in ("artefacts", "heads", "training", "validation_synthetic"):
            if key in d and not isinstance(d[key], dict):
                bad(f"'{key}' is not a mapping")
        if not all(isinstance(k, str) and isinstance(v, str) for k, v in d.get("artefacts", {}).items()):
            bad("'artefacts' must map roles to file names")
        det = d.get("detector")
        if det is not None and (not isinstance(det, dict) or not isinstance(det.get("classes"), list)):
            bad("the detector's 'classes' list is missing")
        typed = {f.name for f in dataclasses.fields(cls)} - {"extra"}
        return cls(name=str(d.get("name", "")), method=str(d.get("method", "?")), input_size=d["input_size"],
                   latent_size=d["latent_size"], objects=objects, artefacts=dict(d.get("artefacts", {})),
                   encoder=str(d.get("encoder", "plain")), pose_prior=str(d.get("pose_prior", "sphere")),
                   training_camera=d.get("training_camera"), detector=det, heads=dict(d.get("heads", {})),
                   training=dict(d.get("training", {})), validation_synthetic=dict(d.get("validation_synthetic", {})),
                   command=d.get("command"), created=d.get("created"), files=dict(files), format=fmt,
                   extra={k: v for k, v in d.items() if k not in typed})

    def to_dict(self) -> dict:
        """The one writer's JSON object (``files`` and ``format`` as they are: the bundle writer
        sets them)."""
        d = {**self.extra, "name": self.name, "method": self.method, "encoder": self.encoder,
             "input_size": self.input_size, "latent_size": self.latent_size, "objects": [o.to_dict() for o in self.objects],
             "training_camera": self.training_camera, "pose_prior": self.pose_prior, "artefacts": self.artefacts,
             "training": self.training, "validation_synthetic": self.validation_synthetic,
             "heads": self.heads, "command": self.command, "created": self.created}
        if self.detector is not None:
            d["detector"] = self.detector
        d["format"], d["files"] = self.format, self.files
        return d

    def copy(self) -> "Manifest":
        """A deep copy to edit (a job that changes a bundle edits a copy, then writes it)."""
        import copy
        return copy.deepcopy(self)

    # ------------------------------------------------------------------ what readers ask

    @property
    def obj_ids(self) -> list[int]:
        return [o.id for o in self.objects]

    def object(self, obj_id: int) -> ObjectEntry:
        for o in self.objects:
            if o.id == int(obj_id):
                return o
        raise UserError(f"object {obj_id} is not in this bundle (has {self.obj_ids})")

    @property
    def has_detector(self) -> bool:
        return self.detector is not None and "detector" in self.artefacts

    def file_sha256(self, role: str) -> str | None:
        rel = self.artefacts.get(role)
        return self.files.get(rel, {}).get("sha256") if rel else None
