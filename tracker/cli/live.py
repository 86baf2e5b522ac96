"""The live pipeline's commands: ``demo`` (the bundled recording), ``track`` (a camera, video,
image folder or BOP scene) and ``bench`` (per-stage latency), with the output options and the
end-of-run summary that demo and track share."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from tracker.cli.args import fraction, nonnegative_float, nonnegative_int, positive_int
from tracker.cli.common import default_run_dir, para
from tracker.core.errors import UserError
from tracker.runtime.confidence import UNCERTAIN_BELOW

RUN_FOLDER_HELP = """the run folder holds:
  poses.csv       one row per pose (BOP results format; score = the pose's confidence)
  timings.csv     one row per frame: capture time and milliseconds per stage
  summary.json    frames, fps, per-stage medians, objects tracked / uncertain / lost, accuracy
                  where the source has ground truth (docs/formats.md)
  recording.rrd   the rerun recording (--rerun save or serve): .venv/bin/rerun FILE
"""


def add_output_options(s, rerun_default: str) -> None:
    """What a run shows and writes besides its logs (track and demo)."""
    s.add_argument("--rerun", choices=["spawn", "serve", "save", "off"], default=rerun_default,
                   help="save: write OUT/recording.rrd (default); serve: a web viewer at the printed URL, "
                        "also saved, kept serving after the run until Ctrl-C or --serve-for; spawn: the native "
                        "viewer (needs a display); off: nothing")
    s.add_argument("--serve-for", type=nonnegative_float, default=None, metavar="SECONDS",
                   help="with --rerun serve: stop serving this long after the run ends (default: at Ctrl-C)")
    s.add_argument("--video-out", metavar="FILE", help="write the annotated frames as a video (.mp4, .avi or .mkv) "
                                                       "at the source's frame rate")
    s.add_argument("--frames-out", metavar="DIR", help="write the annotated frames as numbered PNGs into DIR")
    s.add_argument("--min-confidence", type=fraction, default=UNCERTAIN_BELOW, metavar="C",
                   help=f"poses whose confidence (detector score x code similarity x box agreement) is below C "
                        f"are drawn as uncertain: an outline only, dimmed (default {UNCERTAIN_BELOW})")


def _print_run(s, out: Path) -> None:
    st = s.stages_ms
    print(f"{s.frames} frames, {s.poses} poses, {s.fps} fps end to end"
          + (" (interrupted)" if s.interrupted else "") + (f", {s.dropped_frames} frames dropped" if s.dropped_frames else ""))
    print("median ms per frame: " + ", ".join(f"{k} {v['median']:.1f}" for k, v in st.items() if v["median"] is not None))
    if s.accuracy:
        from tracker.evaluation.report import fmt_num
        a = s.accuracy
        print(f"accuracy against the ground truth ({s.boxes} boxes, {a['n_gt']} instances): ADD(I) "
              f"{fmt_num(a['add_recall'])}, AR_MSSD {fmt_num(a['ar_mssd'])}, AR_MSPD {fmt_num(a['ar_mspd'])}, "
              f"median RE {fmt_num(a['re_median_deg'], 1)} deg, median TE {fmt_num(a['te_median_mm'], 1)} mm")
    lost = [k for k, v in s.objects.items() if v["state_at_end"] == "lost"]
    if s.objects and s.frames:
        print("frames tracked (confident) per object: " + ", ".join(f"{k} {v['tracked']}/{s.frames}"
                                                                    for k, v in s.objects.items())
              + (f"; lost at the end: {', '.join(lost)}" if lost else ""))
    print(f"run folder: {out} (poses.csv, timings.csv, summary.json)")
    if s.video:
        print(f"annotated video: {s.video}")
    if s.frames_dir:
        print(f"annotated frames: {s.frames_dir}/")
    if s.recording:
        print(f"rerun recording: {s.recording}  (open it with: .venv/bin/rerun {s.recording}, "
              f"or headless: .venv/bin/rerun --serve-web {s.recording})")
    if s.camera_reconnects:
        print(f"warning: the camera dropped out and was reopened {s.camera_reconnects} time(s)", file=sys.stderr)
    if s.camera_lost:
        print("warning: the camera stopped delivering frames (unplugged?); the logs above are complete", file=sys.stderr)
    if s.video_truncated:
        print("warning: the video ended before its declared length (truncated file?)", file=sys.stderr)


def _outputs(args) -> dict:
    return dict(video_out=args.video_out, frames_out=args.frames_out, min_confidence=args.min_confidence)


def _hold_viewer(s, args) -> None:
    """--rerun serve: the servers outlive the run until Ctrl-C or --serve-for."""
    if s.viewer is not None:
        s.viewer.hold(args.serve_for, log=lambda m: print(m, file=sys.stderr))


def add_demo(sub, REPO) -> None:
    """``app.py demo``: the bundled recording through the whole pipeline."""
    s = sub.add_parser("demo", help="replay the bundled recording through the pipeline (default)",
                       description=para("The bundled recording (demo/lmo_dev: 50 real LM-O frames as a video, with "
                                        "their ground truth) through the whole pipeline with models/lmo: detector, "
                                        "crops, encoder, regressors, overlay, rerun; accuracy against the ground "
                                        "truth."),
                       epilog=RUN_FOLDER_HELP + "\nexamples:\n  python app.py demo\n"
                              "  python app.py demo --video-out demo.mp4\n"
                              "  python app.py demo --rerun serve          # then open the printed URL\n",
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    s.add_argument("--out", help="run folder (default runs/demo-TIMESTAMP)")
    s.add_argument("--max-frames", type=positive_int, default=None, metavar="N", help="stop after N frames")
    add_output_options(s, rerun_default="save")
    s.set_defaults(func=cmd_demo)


def cmd_demo(args) -> int:
    """The bundled recording (demo/lmo_dev: the LM-O dev frames as a video, with their ground
    truth) through the full pipeline with models/lmo: detector -> crops -> encoder ->
    regressors -> overlay -> rerun; accuracy against the recording's ground truth."""
    from tracker.core.bundle import open_bundle
    from tracker.core.paths import DEMO_RECORDING, REPO
    from tracker.evaluation.track import track
    from tracker.runtime.loop import TrackConfig
    out = Path(args.out) if args.out else default_run_dir("demo")
    bundle = REPO / "models" / "lmo"
    if not (DEMO_RECORDING / "rgb.avi").is_file():
        raise UserError(f"the bundled recording {DEMO_RECORDING} is missing; restore it with git checkout")
    boxes = "detector" if open_bundle(bundle).manifest.has_detector else "gt"
    print(f"demo: {DEMO_RECORDING.relative_to(REPO)} (LM-O dev frames) -> "
          f"{'detector' if boxes == 'detector' else 'ground-truth boxes (no detector in the bundle)'} -> "
          f"models/lmo -> poses, overlay, rerun", file=sys.stderr)
    s = track(TrackConfig(str(DEMO_RECORDING), str(bundle), out, rerun=args.rerun, max_frames=args.max_frames,
                          boxes=boxes, **_outputs(args)), log=lambda m: print(m, file=sys.stderr))
    _print_run(s, out)
    _hold_viewer(s, args)
    return 130 if s.interrupted else 0


def add_track(sub, REPO) -> None:
    """``app.py track``: the frame loop on a camera, video, image folder or BOP scene."""
    s = sub.add_parser("track", help="the frame loop on a camera, video, image folder or BOP scene",
                       description=para("Track a bundle's objects in a camera's frames (V4L2 index or /dev/videoN), "
                                        "a video file, a folder of images or a BOP scene: detector, crops, encoder, "
                                        "regressors, poses, overlay; logged to the run folder and rerun."),
                       epilog=RUN_FOLDER_HELP + "\nexamples:\n"
                              "  python app.py track --source 0 --calib calib/camera.yaml --rerun serve\n"
                              "  python app.py track --source clip.mp4 --calib calib/camera.yaml --video-out clip_poses.mp4\n"
                              "  python app.py track --source ../shared/data/lmo/dev --boxes detector\n"
                              "  python app.py track --source photos/ --calib calib/camera.yaml --model models/duck "
                              "--frames-out shots/\n",
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    s.add_argument("--source", required=True,
                   help="camera index (0) or /dev/videoN, a video file, a folder of images, or a BOP scene folder")
    s.add_argument("--model", default=str(REPO / "models" / "lmo"), help="model bundle (default models/lmo)")
    s.add_argument("--calib", help="camera file from 'app.py calibrate' (needed for cameras, videos and image "
                                   "folders; BOP scenes carry their intrinsics)")
    s.add_argument("--out", help="run folder (default runs/track-TIMESTAMP)")
    s.add_argument("--max-frames", type=positive_int, metavar="N", help="stop after N frames (default: the whole source)")
    s.add_argument("--realtime", action="store_true",
                   help="play recordings at their recorded rate, dropping frames the tracker cannot keep up with "
                        "(default: every frame, as fast as it goes)")
    s.add_argument("--no-overlay", action="store_true", help="skip rendering the overlay (faster; the video and "
                                                             "rerun get the plain frames)")
    s.add_argument("--loop", action="store_true", help="replay a recording again and again up to --max-frames (soak)")
    s.add_argument("--detect-every", type=positive_int, default=1, metavar="N",
                   help="run the detector every N frames (and whenever an object is lost); in between, "
                        "boxes come from the previous poses")
    s.add_argument("--propagate", choices=["off", "join", "all"], default="off",
                   help="on detector frames, the previous frame's pose boxes as candidates, verified by the pose "
                        "pipeline (the most confident pose kept): join: for the objects the detector found; all: "
                        "also for those it missed whose previous pose was confident (--min-confidence)")
    s.add_argument("--smooth", type=float, default=None, metavar="ALPHA",
                   help="temporal smoothing on SO(3) x R^3, 0 < ALPHA <= 1 (smaller = smoother); off by default")
    s.add_argument("--boxes", choices=["auto", "gt", "detector"], default="auto",
                   help="auto: ground truth on BOP scenes that have it, else the bundle's detector")
    add_output_options(s, rerun_default="save")
    s.set_defaults(func=cmd_track)


def cmd_track(args) -> int:
    from tracker.evaluation.track import track
    from tracker.runtime.loop import TrackConfig
    out = Path(args.out) if args.out else default_run_dir("track")
    cfg = TrackConfig(args.source, args.model, out, args.calib, args.rerun, args.max_frames, args.realtime,
                      not args.no_overlay, args.boxes, detect_every=args.detect_every, smooth=args.smooth,
                      loop=args.loop, propagate=args.propagate, **_outputs(args))
    s = track(cfg, log=lambda m: print(m, file=sys.stderr))
    _print_run(s, out)
    _hold_viewer(s, args)
    return 130 if s.interrupted else 0


def add_bench(sub, REPO) -> None:
    """``app.py bench``: per-stage latency of the live pipeline."""
    s = sub.add_parser("bench", help="per-stage latency of the live pipeline")
    s.add_argument("--model", default=str(REPO / "models" / "lmo"))
    s.add_argument("--source", default=str(REPO / "demo" / "lmo_dev"),
                   help="default: the bundled recording")
    s.add_argument("--calib")
    s.add_argument("--frames", type=positive_int, default=50)
    s.add_argument("--boxes", choices=["auto", "gt", "detector"], default="detector",
                   help="detector (default; the real pipeline) or ground-truth boxes")
    s.add_argument("--detect-every", type=positive_int, default=1, metavar="N")
    s.add_argument("--obj-ids", type=int, nargs="+", help="track only these objects (e.g. one, for the 1-object case)")
    s.add_argument("--skip-first", type=nonnegative_int, default=2, help="warm-up frames left out of the statistics")
    s.add_argument("--rerun", choices=["save", "off"], default="save")
    s.add_argument("--no-overlay", action="store_true")
    s.add_argument("--out", help="keep the run folder here")
    s.add_argument("--json", required=True)
    s.set_defaults(func=cmd_bench)


def cmd_bench(args) -> int:
    from tracker.core.bop import check_output_file, write_json
    from tracker.evaluation.bench import bench
    from tracker.runtime.loop import TrackConfig
    check_output_file(args.json, "--json")
    cfg = TrackConfig(args.source, args.model, Path(args.out) if args.out else None, args.calib, args.rerun, args.frames,
                      False, not args.no_overlay, args.boxes, detect_every=args.detect_every, obj_ids=args.obj_ids)
    res, s = bench(cfg, skip_first=args.skip_first, log=lambda m: print(m, file=sys.stderr))
    write_json(args.json, res)
    print(f"{res['frames']} frames, {res['objects_per_frame']} objects/frame: {res['fps']} fps (median), "
          f"{res['ms_per_object']} ms per object (crop + encoder + regressors)")
    print("median / p95 ms: " + ", ".join(f"{k} {v['median']:.1f}/{v['p95']:.1f}" for k, v in res["stages_ms"].items()))
    if s.video_truncated:
        print("warning: the video ended before its declared length (truncated file?)", file=sys.stderr)
    print(("INTERRUPTED after " if s.interrupted else "") + f"{res['frames']} frames: wrote {args.json}")
    return 130 if s.interrupted else 0
