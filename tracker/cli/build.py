"""``app.py build``: a folder of meshes -> a finished tracking bundle in one time budget
(resumable). The training code (tracker.training) is imported only when the command runs."""
from __future__ import annotations

import argparse
import sys

from tracker.cli.args import id_list, nonnegative_int, positive_float, positive_int
from tracker.core.defaults import DETECTOR_BACKBONES
from tracker.cli.common import para
from tracker.core.defaults import SYNTH_FACES
from tracker.core.errors import UserError
from tracker.runtime.signals import sigterm_as_ctrl_c


def add_build(sub, REPO) -> None:
    """``app.py build``: your meshes -> a finished tracking bundle."""
    s = sub.add_parser("build", help="your meshes -> a finished tracking bundle, in one time budget (resumable)",
                       description=para("From a folder of meshes (PLY, OBJ, STL, GLB) to a bundle: the meshes in "
                                        "mm with their symmetries, synthetic training splits, the encoder and its "
                                        "pose heads, the detector, a check on fresh held-out renders and a report "
                                        "(MODEL_DIR/report/report.md). --minutes is split 20 % rendering, 48 % "
                                        "encoder and heads, 30 % detector, 2 % check. Everything intermediate stays "
                                        "in MODEL_DIR.work/; Ctrl-C keeps what is done and the same command resumes."),
                       epilog="examples:\n  python app.py build --models my_meshes/ --out models/mug --minutes 60\n"
                              "  python app.py build --from-manifest models/mug --out models/mug2\n",
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    s.add_argument("--models", help="folder of meshes (files named obj_NNNNNN keep their id; others are numbered)")
    s.add_argument("--out", required=True, help="bundle folder to write, e.g. models/mug")
    s.add_argument("--minutes", type=positive_float, default=60.0, help="the whole job's time budget (default 60)")
    s.add_argument("--objects", type=id_list, help="comma-separated subset of the meshes' ids")
    s.add_argument("--prior", choices=["table", "sphere"], default="table",
                   help="table: objects upright on a surface, seen from above (default); sphere: any orientation "
                        "(hand-held)")
    s.add_argument("--units", choices=["auto", "mm", "cm", "m"], default="auto",
                   help="the meshes' unit; auto refuses a mesh under 5 units across (it looks like metres)")
    s.add_argument("--seed", type=nonnegative_int, default=0)
    s.add_argument("--encoder", choices=["plain", "lite0", "lite1", "lite2"], default="plain",
                   help="the pose encoder's trunk (lite*: ImageNet-pretrained)")
    s.add_argument("--size", type=positive_int, default=64, help="crop side in pixels")
    s.add_argument("--detector-backbone", choices=DETECTOR_BACKBONES, default="nanodet",
                   help="the detector's trunk: nanodet (COCO-pretrained, default), plain (small, from random weights: "
                        "half the detection time, worse on real frames), lite0-2 (ImageNet-pretrained)")
    s.add_argument("--detector-input", type=positive_int, nargs=2, default=[416, 320], metavar=("W", "H"),
                   help="the detector's input size, multiples of 8 (default 416 320; 320 240: the recipe before "
                        "stop 66, faster and worse at box precision)")
    s.add_argument("--detector-int8", action=argparse.BooleanOptionalAction, default=True,
                   help="store the detector int8, calibrated on its training renders (default; --no-detector-int8 "
                        "keeps it float32: the recipe before stop 66)")
    s.add_argument("--workers", type=positive_int,
                   help="render processes (default 2); with --ray, the most training workers and render tasks at "
                        "once (default: every CPU of the cluster, or every GPU for training)")
    s.add_argument("--ray", nargs="?", const="local", metavar="ADDRESS",
                   help="render and train on a Ray cluster: no ADDRESS starts one on this machine for the build, "
                        "'auto' or ray://HOST:PORT joins a running one (needs the 'cluster' extra: "
                        "pip install -e '.[cluster]'; README, Building on a cluster)")
    s.add_argument("--mesh-faces", type=nonnegative_int, default=SYNTH_FACES, metavar="N",
                   help=f"render the objects decimated to about N faces (default {SYNTH_FACES}; 0: the full meshes)")
    s.add_argument("--device", choices=["auto", "cpu", "cuda"], default="auto",
                   help="where the networks train: a CUDA GPU where torch sees one (auto), or the CPU")
    s.add_argument("--head-sets", type=positive_int, default=3, metavar="N",
                   help="pose-head sets fitted with seeds seed, seed+1, ... and averaged (default 3; 1: the recipe "
                        "before stop 51)")
    s.add_argument("--max-images", type=positive_int, metavar="N",
                   help="the most images per rendered split (default: what this machine's memory can train on)")
    s.add_argument("--names", metavar="FILE",
                   help="JSON of object names by id, e.g. {\"9\": \"duck\"} (default: names.json beside the meshes, "
                        "else the file names); kept in the bundle and shown on the overlay, in rerun and the status")
    s.add_argument("--from-manifest", metavar="BUNDLE",
                   help="redo the recipe a built bundle records (its options; only --workers and --device may "
                        "differ: where it runs)")
    s.set_defaults(func=cmd_build, recipe_defaults={k: s.get_default(k) for k in RECIPE_OPTIONS})


# the options that make the bundle (--workers, --device and --ray say where it is made)
RECIPE_OPTIONS = ("models", "minutes", "objects", "prior", "units", "seed", "encoder", "size",
                  "detector_backbone", "detector_input", "detector_int8", "mesh_faces", "head_sets", "max_images",
                  "names")


def cmd_build(args) -> int:
    sigterm_as_ctrl_c()
    from tracker.training.build import Recipe, build, recipe_from_manifest
    if args.from_manifest:
        given = [k for k in RECIPE_OPTIONS if getattr(args, k) != args.recipe_defaults[k]]
        if given:  # before anything is read: the recorded recipe would silently win
            flags = ", ".join("--" + k.replace("_", "-") for k in given)
            raise UserError(f"--from-manifest redoes {args.from_manifest}'s recorded recipe; drop {flags} "
                            f"(or build from --models with the options you want)")
        recipe = recipe_from_manifest(args.from_manifest, log=lambda m: print(m, file=sys.stderr))
        if args.workers:
            recipe.workers = args.workers
        if args.device != args.recipe_defaults.get("device", "auto"):
            recipe.device = args.device
        print(f"build: the recipe of {args.from_manifest}: {recipe}", file=sys.stderr)
    else:
        if not args.models:
            raise UserError("build needs --models DIR (a folder of meshes) or --from-manifest BUNDLE")
        recipe = Recipe(models=str(args.models), minutes=args.minutes, objects=args.objects, prior=args.prior,
                        units=args.units, seed=args.seed, encoder=args.encoder, size=args.size,
                        detector_backbone=args.detector_backbone, detector_input=list(args.detector_input),
                        detector_int8=args.detector_int8, workers=args.workers or 2, device=args.device,
                        mesh_faces=args.mesh_faces, head_sets=args.head_sets, max_images=args.max_images,
                        names=args.names)
    log = lambda m: print(m, file=sys.stderr)  # noqa: E731
    if args.ray:
        from tracker.training.cluster import RayCluster
        with RayCluster(None if args.ray == "local" else args.ray, workers=args.workers, log=log) as cluster:
            s = build(recipe, args.out, log=log, cluster=cluster)
    else:
        s = build(recipe, args.out, log=log)
    det = s["stages"].get("check", {}).get("detector", {})
    print(f"built {args.out} in {s['minutes']} min this run, {s['minutes_all_runs']} min over all its runs "
          f"(budget {s['budget_minutes']:g}): on held-out renders "
          f"with its detector ADD(I) {det.get('add_recall', float('nan')):.3f}, AR_MSPD {det.get('ar_mspd', float('nan')):.3f}; "
          f"report {s['report']}")
    return 0
