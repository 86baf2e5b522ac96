"""``app.py synth``: synthetic, domain-randomised BOP training scenes. The rendering code
(tracker.training) is imported only when the command runs."""
from __future__ import annotations

import sys
from pathlib import Path

from tracker.cli.args import id_list, nonnegative_int, positive_int, shard_spec
from tracker.core.defaults import SYNTH_FACES
from tracker.core.errors import UserError
from tracker.runtime.signals import sigterm_as_ctrl_c


def add_synth(sub, REPO) -> None:
    """``app.py synth``: synthetic training scenes."""
    s = sub.add_parser("synth", help="synthetic, domain-randomised BOP training scenes")
    s.add_argument("--models", required=True, help="folder of obj_NNNNNN.ply (mm)")
    s.add_argument("--out", required=True, help="output split folder")
    s.add_argument("--images", type=positive_int, required=True, help="number of scene images")
    s.add_argument("--seed", type=nonnegative_int, default=0)
    s.add_argument("--backgrounds", help="folder of background photos (default: the shared data's)")
    s.add_argument("--prior", choices=["table", "sphere"], default="table",
                   help="pose prior: objects upright on a table (LM-O) or any orientation (hand-held)")
    s.add_argument("--p-table", type=float, default=0.7, metavar="P",
                   help="table prior: share of scenes with the table's surface and shadows drawn "
                        "(0: photos behind floating objects, as data made before it existed)")
    s.add_argument("--gloss", type=float, default=0.0, metavar="P",
                   help="share of objects per image rendered glossy and partly metallic, with highlights "
                        "(0: matte only, as data made before it existed)")
    s.add_argument("--colour-jitter", type=float, default=0.15, metavar="S",
                   help="each object's colours scaled per channel by 1 +- S, and its saturation changed "
                        "(default 0.15; 0: the objects' own colours, the same scenes)")
    s.add_argument("--no-camera-effects", dest="camera_effects", action="store_false",
                   help="no exposure, contrast, saturation, white balance, blur or sensor noise (on by default; "
                        "the same scenes either way)")
    s.add_argument("--distractors", choices=["plain", "hard", "household"], default="plain",
                   help="plain: 0-5 random primitives per image (as data made before); hard: 2-8 primitives "
                        "textured from the photos and tinted, half the time with the targets' colours; "
                        "household: as hard, half of the shapes mugs, cups and bottles")
    s.add_argument("--occluders", metavar="DIR",
                   help="folder of household meshes (.ply/.obj, mm, vertex colours; scripts/debian_assets.py "
                        "furniture): distractors and occluders drawn from it in their own colours, as many as "
                        "--distractors draws (default: the style's shapes)")
    s.add_argument("--lighting", choices=["camera", "overhead"], default="camera",
                   help="camera: 1-3 lights from the camera's side (as data made before); overhead: a strong "
                        "key light from above the table, a weak fill, little ambient (bright tops, dark sides)")
    s.add_argument("--obj-ids", type=id_list, help="comma-separated subset of the models' ids")
    s.add_argument("--repeat-objects", action="store_true",
                   help="with fewer objects than an image holds (3-8): several instances of each object per "
                        "image, so one or two objects give as many crops per image as eight")
    s.add_argument("--workers", type=positive_int, default=2, help="render processes")
    s.add_argument("--shard", type=shard_spec, metavar="K/N",
                   help="render only the K-th of N disjoint parts of the split (K = 0 .. N-1), e.g. one per "
                        "machine of a cluster's array job; 'app.py lab join-splits' joins the parts into the "
                        "same images as one run")
    s.add_argument("--depth", action="store_true", help="also write depth images (depth/, for VSD)")
    s.add_argument("--mesh-faces", type=nonnegative_int, default=None, metavar="N",
                   help="render the objects decimated to about N faces: the CPU rasteriser's cost grows with "
                        f"triangles (default {SYNTH_FACES}; 0: the full meshes; docs/experiments/stop-47.md)")
    s.add_argument("--preview", help="PNG montage of samples, boxes, visible fractions and crops")
    s.set_defaults(func=cmd_synth)


def cmd_synth(args) -> int:
    sigterm_as_ctrl_c()
    from tracker.core.paths import shared_data
    from tracker.training.synth.engine import DEFAULT_MESH_FACES, SynthConfig, generate
    from tracker.training.synth.preview import preview
    obj_ids = args.obj_ids
    if args.preview and (Path(args.preview).is_dir() or Path(args.preview).suffix.lower() not in (".png", ".jpg", ".jpeg")):
        raise UserError(f"--preview {args.preview}: name a .png or .jpg file")  # before the rendering, not after
    cfg = SynthConfig(models_dir=str(args.models), backgrounds_dir=str(args.backgrounds or shared_data() / "backgrounds"),
                      seed=args.seed, prior=args.prior, obj_ids=obj_ids, depth=args.depth,
                      mesh_faces=DEFAULT_MESH_FACES if args.mesh_faces is None else (args.mesh_faces or None),
                      p_table=args.p_table, p_gloss=args.gloss, colour_jitter=args.colour_jitter,
                      camera_effects=args.camera_effects,
                      distractors=args.distractors, occluders_dir=args.occluders,
                      lighting=args.lighting, repeat_objects=args.repeat_objects)
    rep = generate(cfg, args.out, args.images, workers=args.workers, command="app.py " + " ".join(sys.argv[1:]),
                   shard=args.shard)
    state = "INTERRUPTED after" if rep.interrupted else "wrote"
    print(f"{state} {rep.images} images, {rep.instances} instances ({rep.crops_visib_ge_0_1} with visib >= 0.1) "
          f"in {rep.seconds:.0f} s: {rep.images_per_s:.1f} images/s, {rep.crops_per_s:.1f} crops/s, "
          f"peak RSS {rep.peak_rss_mb_parent:.0f} MB (main) / {rep.peak_rss_mb_worker:.0f} MB (worker)")
    if args.preview and rep.images:
        print(f"preview: {preview(args.out, args.preview)}")
    return 130 if rep.interrupted else 0
