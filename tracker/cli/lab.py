"""Research tools: ``app.py lab COMMAND`` (``app.py lab --help``). Joins, refits and tuning of
bundles, ablations, and data helpers; kept out of the user's ``--help``."""
from __future__ import annotations

import sys
from pathlib import Path

from tracker.cli.args import (add_join, add_regressor_budget, fraction, jpeg_quality, nonnegative_int,
                              positive_float, positive_int)
from tracker.cli.common import default_run_dir as _default_run_dir
from tracker.cli.common import print_validation as _print_validation


def _print_preview(s) -> None:
    print(f"{s.frames} frames, {s.instances} object instances rendered at their ground-truth poses "
          f"({s.ms_per_frame_render:.0f} ms/frame render)")
    print(f"silhouette vs projected-vertex box IoU over the {s.instances_in_view} instances in view: "
          f"median {s.box_iou_median:.3f}, min {s.box_iou_min:.3f}; "
          f"object centres inside the image: {s.centres_in_image}/{s.instances}")
    print(f"overlays: {s.frames_dir}\nmontage:  {s.montage}")


def cmd_join_splits(args) -> int:
    from tracker.training.synth.join import join_splits
    m = join_splits(args.out, args.splits, command="app.py " + " ".join(sys.argv[1:]))
    print(f"wrote {args.out}: {m['scenes']} scenes, {m['images_written']} images "
          f"from {len(args.splits)} splits (linked, not copied)")
    return 0


def cmd_refit_heads(args) -> int:
    from tracker.training.train import refit_heads
    m = refit_heads(args.model, args.data, out_dir=args.out, seed=args.seed, reg_minutes=args.reg_minutes,
                    keep_regressors=args.keep_regressors, jitter_scale=args.jitter_scale, reg_epochs=args.reg_epochs,
                    command="app.py " + " ".join(sys.argv[1:]))
    _print_validation(args.out or args.model, m)
    return 0


def cmd_join_heads(args) -> int:
    from tracker.research.head_ensemble import join_heads
    join_heads(args.model, args.heads_from, out_dir=args.out, command="app.py " + " ".join(sys.argv[1:]))
    return 0


def cmd_join_detectors(args) -> int:
    from tracker.training.detector_ensemble import join_detectors
    extra = {"calibration_images": args.calibration_images} if args.calibration_images else {}
    if args.score_thresh is not None:
        extra["score_thresh"] = args.score_thresh
    join_detectors(args.model, args.detectors_from, out_dir=args.out, int8_data=args.int8, mirror=args.mirror,
                   weight_bits=args.weight_bits, half=args.half_weights, command="app.py " + " ".join(sys.argv[1:]),
                   **extra)
    return 0


def cmd_fuse_detectors(args) -> int:
    from tracker.training.detector_fusion import fuse_detectors
    fuse_detectors(args.model, args.detectors_from, out_dir=args.out, score_thresh=args.score_thresh, iou=args.iou,
                   floor=args.floor, command="app.py " + " ".join(sys.argv[1:]))
    return 0


def cmd_requantise_detector(args) -> int:
    from tracker.training.detector_ensemble import requantise_detector
    extra = {"calibration_images": args.calibration_images} if args.calibration_images else {}
    requantise_detector(args.model, args.int8, out_dir=args.out, weight_bits=args.weight_bits,
                        command="app.py " + " ".join(sys.argv[1:]), **extra)
    return 0


def cmd_tune_heads(args) -> int:
    from tracker.research.tune_heads import WEIGHTS, tune_trees_weight
    tune_trees_weight(args.model, args.data, weights=args.weights or WEIGHTS, out_dir=args.out,
                      max_frames=args.max_frames, command="app.py " + " ".join(sys.argv[1:]))
    return 0


def cmd_ablate(args) -> int:
    from tracker.research.ablate import ablate
    ablate(args.model, args.data, args.json, mlp_minutes=args.mlp_minutes, max_train=args.max_train, seed=args.seed)
    print(f"wrote {args.json}")
    return 0


def cmd_decimate(args) -> int:
    from tracker.training.decimate import add_overlay_meshes
    add_overlay_meshes(args.model, args.faces)
    print(f"{args.model}: overlay meshes of about {args.faces} faces added, manifest re-hashed")
    return 0


def cmd_pack_scene(args) -> int:
    from tracker.runtime.recording import write_scene_video
    r = write_scene_video(args.data, args.out, quality=args.quality, fps=args.fps)
    print(f"wrote {r['video']}: {r['frames']} frames, {r['bytes'] / 1e6:.1f} MB, "
          f"PSNR vs the originals min {r['psnr_min']:.1f} dB, median {r['psnr_median']:.1f} dB")
    return 0


def cmd_resize_scene(args) -> int:
    from tracker.evaluation.scene_copy import resize_scene
    r = resize_scene(args.data, args.out, *args.size)
    left = f" (not copied: {', '.join(r['left_out'])}/)" if r["left_out"] else ""
    print(f"wrote {r['out']}: {r['frames']} frames at {r['size'][0]}x{r['size'][1]}, intrinsics scaled{left}")
    return 0


def cmd_preview(args) -> int:
    from tracker.evaluation.preview import render_gt_overlays
    out = Path(args.out) if args.out else _default_run_dir("preview")
    _print_preview(render_gt_overlays(args.data, args.models, out, max_frames=args.max_frames))
    return 0


def cmd_models_info(args) -> int:
    from tracker.core.bop import save_models_info
    from tracker.core.meshes import compute_models_info, load_models
    info = compute_models_info(load_models(args.models))
    save_models_info(args.out, info)
    for k, v in info.items():
        n = len(v.get("symmetries_discrete", []))
        print(f"obj {k}: diameter {v['diameter']:.2f} mm, {n} discrete symmetr{'y' if n == 1 else 'ies'}")
    print(f"wrote {args.out}")
    return 0


def cmd_prepare_models(args) -> int:
    from tracker.training.prepare import prepare_models
    rep = prepare_models(args.models, args.out, units=args.units, names=args.names, log=print)
    print(f"wrote {args.out}: {len(rep)} object(s) in millimetres, models_info.json, names.json")
    return 0


def cmd_compare(args) -> int:
    from tracker.core.bop import check_output_file, write_json
    from tracker.evaluation.compare import compare_files
    check_output_file(args.json, "--json")
    r = compare_files(args.a, args.b, n_boot=args.bootstrap, seed=args.seed)
    write_json(args.json, r)
    print(f"B - A over {r['n_instances']} instances in {r['n_frames']} frames (paired bootstrap over frames, "
          f"{r['bootstrap']} resamples, 95 % interval):")
    for name, f in r["figures"].items():
        print(f"  {name:>10}  A {f['a']:.4f}  B {f['b']:.4f}  diff {f['diff']:+.4f}  [{f['ci'][0]:+.4f}, {f['ci'][1]:+.4f}]")
    v = r["verdict"]
    print(("keep B" if v["keep_b"] else "keep A") + f" ({v['rule']})"
          + (f"; falls: {', '.join(v['falls'])}" if v["falls"] else ""))
    print(f"wrote {args.json}")
    return 0


def cmd_oracle(args) -> int:
    from tracker.core.bop import check_output_file, write_json
    from tracker.evaluation.oracle import oracle_swaps
    check_output_file(args.json, "--json")
    r = oracle_swaps(args.results, args.data, args.models, models_info=args.models_info,
                     n_boot=args.bootstrap, log=lambda m: print(m, file=sys.stderr))
    write_json(args.json, r)
    a = r["as_estimated"]
    figs = ("add_recall", "ar_mssd", "ar_mspd")
    print(f"{'':>18}" + "".join(f"{h:>30}" for h in ("ADD(I)", "AR_MSSD", "AR_MSPD", "mean")))
    print(f"{'as estimated':>18}" + "".join(f"{a[f] or 0:>30.3f}" for f in figs)
          + f"{sum(a[f] or 0 for f in figs) / 3:>30.3f}")
    for part, v in r["swaps"].items():
        c = v["compare"]["figures"]
        print(f"{'true ' + part:>18}" + "".join(
            f"{c[f]['b']:>8.3f} {c[f]['diff']:+.3f} [{c[f]['ci'][0]:+.3f}, {c[f]['ci'][1]:+.3f}]"
            for f in (*figs, "mean")))
    print(f"(each part of every pose replaced by the ground truth's; B - A with its paired-bootstrap 95 % "
          f"interval over frames)\nwrote {args.json}")
    return 0


def add_commands(sub, REPO) -> None:
    """The research tools, each a sub-parser of ``sub`` (the ``lab`` group)."""
    s = sub.add_parser("join-splits", help="one training split made of several 'synth' splits (linked)")
    s.add_argument("splits", nargs="+", type=Path, help="'synth' splits, in order")
    s.add_argument("--out", type=Path, required=True, help="new folder")
    s.set_defaults(func=cmd_join_splits)

    s = sub.add_parser("refit-heads", help="refit a bundle's regressors and AAE codebook on its frozen encoder")
    s.add_argument("--model", required=True, help="bundle folder, e.g. models/lmo")
    s.add_argument("--data", required=True, help="the 'synth' split to fit on (the bundle's own, normally)")
    s.add_argument("--out", help="write the refitted bundle here (default: in place)")
    add_regressor_budget(s)
    s.add_argument("--keep-regressors", action="store_true",
                   help="keep the rotation, centre and distance regressors; fit only the distance-from-rotation "
                        "trees and the codebook")
    s.add_argument("--jitter-scale", type=positive_float,
                   help="log-size noise (standard deviation) of the jittered training boxes (default: the "
                        "autoencoder's, 0.08)")
    s.add_argument("--seed", type=nonnegative_int, default=0)
    s.set_defaults(func=cmd_refit_heads)

    s = sub.add_parser("join-heads", help="one pose head averaging the head sets of bundles that share an encoder")
    add_join(s, "bundle folder whose encoder, codebook and detector are kept", "heads_from",
              "bundles with the same encoder (e.g. from 'refit-heads --out DIR') whose heads join")
    s.set_defaults(func=cmd_join_heads)

    s = sub.add_parser("join-detectors", help="one detector averaging the detectors of several bundles (optionally int8 "
                                                "or with float16 weights), or one network stored so")
    add_join(s, "bundle folder that gets the joined detector (its own is the first member)", "detectors_from",
              "bundles whose detectors (same classes and input; each keeps its own normalisation) join", required=False)
    s.add_argument("--mirror", choices=("none", "both", "alternate"), default="none",
                   help="mirror images too: 'both' averages every network on the image and its mirror image "
                        "(twice the work; one network needs no --from then), 'alternate' shows the networks the "
                        "image and the mirror image by turns (no extra work)")
    s.add_argument("--int8", metavar="SPLIT", help="quantise the joined detector to int8, calibrated on this synth split")
    s.add_argument("--calibration-images", type=positive_int,
                   help="images of the --int8 split to calibrate on, spread evenly over it (default: 200)")
    s.add_argument("--weight-bits", type=int, choices=(7, 8), default=8,
                   help="bits of the int8 weights (with --int8): 7 cannot saturate the int16 sums of a CPU "
                        "without VNNI (AVX2), which 8 can (default 8)")
    s.add_argument("--half-weights", action="store_true",
                   help="store the joined graph's weights in float16, computed in float32 (half the file, no "
                        "int8 arithmetic; instead of --int8)")
    s.add_argument("--score-thresh", type=float, metavar="T",
                   help="run-time score threshold of the joined detector (default: the first member's)")
    s.set_defaults(func=cmd_join_detectors)

    s = sub.add_parser("fuse-detectors", help="a detector that runs several bundles' detectors on every frame and "
                                                "fuses their detections (networks of other inputs too)")
    add_join(s, "bundle folder that gets the fused detector (its own is the first network)", "detectors_from",
             "bundles whose detectors (the same objects and kind of box) join")
    from tracker.runtime.fusion import Fusion
    s.add_argument("--score-thresh", type=fraction, default=Fusion.score_thresh, metavar="T",
                   help="run-time threshold of a fused detection: the sum of the networks' scores over their "
                        f"number (default {Fusion.score_thresh})")
    s.add_argument("--iou", type=fraction, default=Fusion.iou,
                   help=f"overlap at which detections join (default {Fusion.iou})")
    s.add_argument("--floor", type=fraction, default=Fusion.floor,
                   help=f"each network's lowest score that can join (default {Fusion.floor})")
    s.set_defaults(func=cmd_fuse_detectors)

    s = sub.add_parser("requantise-detector", help="quantise a bundle's int8 detector again from its float32 graph "
                                                   "(by default with 7-bit weights)")
    s.add_argument("--model", required=True, help="bundle folder with an int8 detector")
    s.add_argument("--int8", required=True, metavar="SPLIT", help="synth split to calibrate on (renders, never "
                                                                   "the evaluation frames)")
    s.add_argument("--calibration-images", type=positive_int,
                   help="images of the split to calibrate on, spread evenly over it (default: 200)")
    s.add_argument("--weight-bits", type=int, choices=(7, 8), default=7,
                   help="bits of the int8 weights (default 7: no int16 saturation on a CPU without VNNI)")
    s.add_argument("--out", help="write the bundle here (default: in place)")
    s.set_defaults(func=cmd_requantise_detector)

    s = sub.add_parser("tune-heads", help="choose on renders how much the distance leans on the trees for detector boxes")
    s.add_argument("--model", required=True, help="bundle folder with a detector")
    s.add_argument("--data", required=True, help="a 'synth' split or scene (renders no training used; never the "
                                                 "evaluation frames)")
    s.add_argument("--weights", type=float, nargs="+", metavar="W", help="the trees' shares to try (default 0 0.25 0.5 0.75)")
    s.add_argument("--max-frames", type=positive_int, default=None, help="images per scene (default: all)")
    s.add_argument("--out", help="write the tuned bundle here (default: in place)")
    s.set_defaults(func=cmd_tune_heads)

    s = sub.add_parser("ablate", help="regressor ablations (thesis Tables 4.1, 4.2) on the synthetic validation split")
    s.add_argument("--model", required=True, help="bundle whose frozen encoder gives the latent codes")
    s.add_argument("--data", required=True, help="the 'synth' split the bundle was trained on")
    s.add_argument("--json", required=True, help="where the tables go (the report command reads it)")
    s.add_argument("--mlp-minutes", type=positive_float, default=1.0, help="time budget of each MLP")
    s.add_argument("--max-train", type=positive_int, default=20000, help="subsample the training crops to this many")
    s.add_argument("--seed", type=nonnegative_int, default=0)
    s.set_defaults(func=cmd_ablate)

    s = sub.add_parser("decimate", help="add light overlay meshes (quadric decimation) to a bundle")
    s.add_argument("--model", required=True)
    s.add_argument("--faces", type=positive_int, default=1500, help="target triangle count per object")
    s.set_defaults(func=cmd_decimate)

    s = sub.add_parser("pack-scene", help="a BOP scene as a recording: frames in one MJPEG video + its JSON files")
    s.add_argument("--data", required=True, help="BOP scene folder")
    s.add_argument("--out", required=True, help="recording folder (rgb.avi, scene_camera.json, scene_gt.json)")
    s.add_argument("--quality", type=jpeg_quality, default=95, help="JPEG quality of the frames")
    s.add_argument("--fps", type=positive_float, default=10.0, help="frame rate written into the video")
    s.set_defaults(func=cmd_pack_scene)

    s = sub.add_parser("resize-scene", help="a BOP scene read out at another resolution: frames resized, "
                                            "intrinsics scaled, poses kept (eval it like the original)")
    s.add_argument("--data", required=True, help="BOP scene folder")
    s.add_argument("--out", required=True, help="the copy's folder")
    s.add_argument("--size", type=positive_int, nargs=2, required=True, metavar=("W", "H"), help="the copy's frame size")
    s.set_defaults(func=cmd_resize_scene)

    s = sub.add_parser("preview", help="render a BOP scene's ground-truth poses over its frames")
    s.add_argument("--data", required=True, help="BOP scene folder")
    s.add_argument("--models", required=True, help="folder of obj_NNNNNN.ply")
    s.add_argument("--out", help="output folder")
    s.add_argument("--max-frames", type=positive_int, default=None)
    s.set_defaults(func=cmd_preview)

    s = sub.add_parser("prepare-models", help="your meshes (PLY, OBJ, STL, GLB) -> a BOP models folder in mm")
    s.add_argument("--models", required=True, help="folder of meshes; files named obj_NNNNNN keep their id")
    s.add_argument("--out", required=True, help="models folder to write (obj_NNNNNN.ply, models_info.json, names.json)")
    s.add_argument("--units", choices=["auto", "mm", "cm", "m"], default="auto",
                   help="the meshes' unit; auto refuses a mesh under 5 units across (it looks like metres)")
    s.add_argument("--names", metavar="FILE",
                   help="JSON of object names by id, e.g. {\"9\": \"duck\"} (default: names.json beside the meshes, "
                        "else the file names)")
    s.set_defaults(func=cmd_prepare_models)

    s = sub.add_parser("compare", help="two 'eval --per-instance' files of one scene: each figure's difference "
                                       "with a paired-bootstrap 95 %% interval over frames, and the keep rule")
    s.add_argument("a", help="per-instance CSV of the baseline (A)")
    s.add_argument("b", help="per-instance CSV of the variant (B)")
    s.add_argument("--json", required=True, help="comparison JSON to write")
    s.add_argument("--bootstrap", type=positive_int, default=10000, metavar="N", help="resamples (default 10000)")
    s.add_argument("--seed", type=nonnegative_int, default=0)
    s.set_defaults(func=cmd_compare)

    s = sub.add_parser("oracle", help="what limits a set of poses: each part (rotation, translation, depth, viewing "
                                      "ray) replaced by the ground truth's in turn, scored and compared")
    s.add_argument("--results", required=True, help="BOP results CSV (e.g. eval's --bop-csv)")
    s.add_argument("--data", required=True, help="BOP scene folder with ground truth")
    s.add_argument("--models", required=True, help="folder of obj_NNNNNN.ply")
    s.add_argument("--models-info", help="models_info.json (default: the models folder's, else computed)")
    s.add_argument("--json", required=True, help="JSON to write: each variant's metrics and comparison")
    s.add_argument("--bootstrap", type=positive_int, default=10000, metavar="N", help="resamples (default 10000)")
    s.set_defaults(func=cmd_oracle)

    s = sub.add_parser("models-info", help="compute BOP models_info.json (diameter, box, symmetries)")
    s.add_argument("--models", required=True, help="folder of obj_NNNNNN.ply")
    s.add_argument("--out", required=True, help="models_info.json to write")
    s.set_defaults(func=cmd_models_info)
