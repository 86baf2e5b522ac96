"""The user's jobs: ``app.py COMMAND`` (``app.py --help`` lists them)."""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from tracker.cli.args import (add_precision, add_regressor_budget, finite_float, fraction, id_list, nonnegative_float,
                              nonnegative_int, positive_float, positive_int, shard_spec)
from tracker.training.decimate import SYNTH_FACES
from tracker.training.nets.schedule import LR_SCHEDULES
from tracker.core.errors import UserError
from tracker.runtime.confidence import UNCERTAIN_BELOW
from tracker.runtime.signals import sigterm_as_ctrl_c


def _default_run_dir(name: str) -> Path:
    from tracker.core.paths import REPO
    return REPO / "runs" / f"{name}-{time.strftime('%Y%m%d-%H%M%S')}"


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


def _print_validation(out, manifest) -> None:
    v = manifest.validation_synthetic
    print(f"wrote {out}: synthetic validation median RE {v['regression']['re_median_deg']:.1f} deg "
          f"(AAE {v['aae']['re_median_deg']:.1f}), median TE {v['regression']['te_median_mm']:.1f} mm "
          f"(AAE {v['aae']['te_median_mm']:.1f})")


def cmd_demo(args) -> int:
    """The bundled recording (demo/lmo_dev: the LM-O dev frames as a video, with their ground
    truth) through the full pipeline with models/lmo: detector -> crops -> encoder ->
    regressors -> overlay -> rerun; accuracy against the recording's ground truth."""
    from tracker.core.bundle import open_bundle
    from tracker.core.paths import DEMO_RECORDING, REPO
    from tracker.evaluation.track import track
    from tracker.runtime.loop import TrackConfig
    out = Path(args.out) if args.out else _default_run_dir("demo")
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


def _outputs(args) -> dict:
    return dict(video_out=args.video_out, frames_out=args.frames_out, min_confidence=args.min_confidence)


def _hold_viewer(s, args) -> None:
    """--rerun serve: the servers outlive the run until Ctrl-C or --serve-for."""
    if s.viewer is not None:
        s.viewer.hold(args.serve_for, log=lambda m: print(m, file=sys.stderr))


def cmd_track(args) -> int:
    from tracker.evaluation.track import track
    from tracker.runtime.loop import TrackConfig
    out = Path(args.out) if args.out else _default_run_dir("track")
    cfg = TrackConfig(args.source, args.model, out, args.calib, args.rerun, args.max_frames, args.realtime,
                      not args.no_overlay, args.boxes, detect_every=args.detect_every, smooth=args.smooth,
                      loop=args.loop, **_outputs(args))
    s = track(cfg, log=lambda m: print(m, file=sys.stderr))
    _print_run(s, out)
    _hold_viewer(s, args)
    return 130 if s.interrupted else 0


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


def cmd_calibrate(args) -> int:
    from tracker.core.calibration import calibrate, parse_board
    from tracker.core.camera import write_camera
    if not args.images and args.source is None:
        raise UserError("calibrate needs --images GLOB or --source SRC")
    board = parse_board(args.board)
    if Path(args.out).is_dir():
        raise UserError(f"--out {args.out} is a folder; give the camera file to write, e.g. {Path(args.out) / 'camera.yaml'}")
    res = calibrate(board, args.square, images=args.images, source=args.source, every=args.every,
                    log=lambda m: print(m, file=sys.stderr))
    write_camera(args.out, res.camera, {"avg_reprojection_error": res.rms_px, "nframes": len(res.used),
                                        "board_width": board[0], "board_height": board[1],
                                        "square_size_mm": args.square})
    K = res.camera.K
    print(f"{len(res.used)} views used, {len(res.skipped)} skipped; RMS re-projection error "
          f"{res.rms_px:.3f} px; fx {K[0, 0]:.2f} fy {K[1, 1]:.2f} cx {K[0, 2]:.2f} cy {K[1, 2]:.2f}")
    print(f"wrote {args.out}")
    return 0


def cmd_imu(args) -> int:
    from tracker.evaluation.imu import compare, read_imu_log, read_run, write_report
    run = read_run(args.run, obj_id=args.obj_id)
    log = read_imu_log(args.imu, max_gap_s=args.max_gap)
    rep = compare(run, log, mode=args.mode, time_offset_s=args.time_offset, max_offset_s=args.max_offset)
    files = write_report(args.out, rep)
    print(f"{rep['n_pairs']} frame/IMU pairs, clock offset {rep['time_offset_s'] * 1000:.1f} ms: RE mean "
          f"{rep['re_mean_deg']:.2f} deg, median {rep['re_median_deg']:.2f}, p90 {rep['re_p90_deg']:.2f}, "
          f"max {rep['re_max_deg']:.2f} ({args.mode} mode)")
    print("wrote " + ", ".join(str(p) for p in files.values()))
    return 0


def cmd_eval(args) -> int:
    from tracker.evaluation.evaluate import evaluate
    m = evaluate(args.model, args.data, args.json, boxes=args.boxes, mode=args.mode, bop_csv=args.bop_csv,
                 max_frames=args.max_frames, gt_models=args.gt_models)
    from tracker.evaluation.report import fmt_num
    print(f"{m['method']} on {m['n_gt']} instances ({m['boxes']} boxes): ADD(I) {fmt_num(m['add_recall'])}, "
          f"AR_MSSD {fmt_num(m['ar_mssd'])}, AR_MSPD {fmt_num(m['ar_mspd'])}, RE median {fmt_num(m['re_median_deg'], 1)} "
          f"deg, TE median {fmt_num(m['te_median_mm'], 1)} mm, {fmt_num(m['ms_per_image'], 1)} ms/image")
    print(f"{'obj':>5} {'ADD(I)':>7} {'MSSD':>6} {'MSPD':>6} {'RE':>6} {'TE':>7}")
    for k, v in sorted(m["per_object"].items(), key=lambda kv: int(kv[0])):
        if v.get("add_recall") is None:
            continue
        print(f"{k:>5} {fmt_num(v['add_recall']):>7} {fmt_num(v['ar_mssd']):>6} {fmt_num(v['ar_mspd']):>6} "
              f"{fmt_num(v['re_median_deg'], 1):>6} {fmt_num(v['te_median_mm'], 1):>7}")
    d = m.get("detection")
    if d:
        op = d["operating_point"]
        print(f"detector: AP {fmt_num(d['ap'])}, AP50 {fmt_num(d['ap50'])}, recall50 {fmt_num(d['recall50'])} "
              f"(COCO: ranked candidates); as the loop runs it (one per object, manifest threshold): AP "
              f"{fmt_num(op['ap'])}, AP50 {fmt_num(op['ap50'])}, recall50 {fmt_num(op['recall50'])}; "
              f"{d['ms_per_image_median']:.1f} ms/image (median)")
        print(f"{'obj':>5} {'AP':>6} {'AP50':>6} {'R50':>6}")
        for k, v in sorted(d["per_object"].items(), key=lambda kv: int(kv[0])):
            if v["n_gt"]:
                print(f"{k:>5} {fmt_num(v['ap']):>6} {fmt_num(v['ap50']):>6} {fmt_num(v['recall50']):>6}")
    print(f"visibility: {m['visibility_source']}\nwrote {args.json} and {m['bop_csv']}")
    return 0


def cmd_score(args) -> int:
    from tracker.core.bop import check_output_file
    from tracker.evaluation.scoring import score_results, write_metrics_json
    check_output_file(args.json, "--json")
    m = score_results(args.results, args.data, args.models, models_info=args.models_info)
    write_metrics_json(args.json, m)
    from tracker.evaluation.report import fmt_num  # (no instances: the recalls are null)
    print(f"{m['n_gt']} ground-truth instances, {m['n_est']} estimates: ADD(I) {fmt_num(m['add_recall'])}, "
          f"AR_MSSD {fmt_num(m['ar_mssd'])}, AR_MSPD {fmt_num(m['ar_mspd'])}, AR {fmt_num(m['ar'])} "
          f"(visibility: {m['visibility_source']})")
    print(f"wrote {args.json}")
    return 0


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
                      p_table=args.p_table, p_gloss=args.gloss, distractors=args.distractors,
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


def cmd_train(args) -> int:
    sigterm_as_ctrl_c()
    from tracker.training.train import train_bundle
    m = train_bundle(args.data, args.out, method=args.method, size=args.size, latent=args.latent,
                     minutes=args.minutes, seed=args.seed, max_images=args.max_images,
                     models_info_path=args.models_info, reg_minutes=args.reg_minutes, encoder=args.encoder,
                     init_from=args.init_from, precision=args.precision, reg_epochs=args.reg_epochs,
                     lr=args.lr, batch=args.batch, pretrained=not args.no_pretrained, device=args.device,
                     kl_warmup=args.kl_warmup, lr_schedule=args.lr_schedule, head_sets=args.head_sets,
                     command="app.py " + " ".join(sys.argv[1:]))
    if m is None:  # a helper process of a torchrun job: the first process writes the bundle
        return 0
    _print_validation(args.out, m)
    return 0


def cmd_build(args) -> int:
    sigterm_as_ctrl_c()
    from tracker.training.build import Recipe, build, recipe_from_manifest
    if args.from_manifest:
        recipe = recipe_from_manifest(args.from_manifest)
        print(f"build: the recipe of {args.from_manifest}: {recipe}", file=sys.stderr)
    else:
        if not args.models:
            raise UserError("build needs --models DIR (a folder of meshes) or --from-manifest BUNDLE")
        recipe = Recipe(models=str(args.models), minutes=args.minutes, objects=args.objects, prior=args.prior,
                        units=args.units, seed=args.seed, encoder=args.encoder, size=args.size,
                        detector_backbone=args.detector_backbone, workers=args.workers, device=args.device,
                        mesh_faces=args.mesh_faces, head_sets=args.head_sets, max_images=args.max_images)
    s = build(recipe, args.out, log=lambda m: print(m, file=sys.stderr))
    det = s["stages"].get("check", {}).get("detector", {})
    print(f"built {args.out} in {s['minutes']} min this run, {s['minutes_all_runs']} min over all its runs "
          f"(budget {s['budget_minutes']:g}): on held-out renders "
          f"with its detector ADD(I) {det.get('add_recall', float('nan')):.3f}, AR_MSPD {det.get('ar_mspd', float('nan')):.3f}; "
          f"report {s['report']}")
    return 0


def cmd_train_detector(args) -> int:
    sigterm_as_ctrl_c()
    from tracker.training.detector_train import train_detector
    d = train_detector(args.data, args.model, minutes=args.minutes, width=args.width, input_w=args.input[0],
                       input_h=args.input[1], batch=args.batch, seed=args.seed, max_images=args.max_images,
                       lr=args.lr, init_from=args.init_from, occlusion=args.occlusion, paste_objects=args.paste_objects,
                       cutouts=args.cutouts, cutout_share=args.cutout_share,
                       precision=args.precision, box_kind=args.boxes, colour=args.colour, ema=args.ema,
                       backbone=args.backbone, pretrained=not args.no_pretrained, device=args.device,
                       command="app.py " + " ".join(sys.argv[1:]))
    if d is None:  # a helper process of a torchrun job: the first process writes the bundle
        return 0
    v = d["training"]["validation_synthetic"]
    from tracker.evaluation.report import fmt_num
    print(f"detector added to {args.model}: synthetic validation AP {fmt_num(v['ap'])}, AP50 {fmt_num(v['ap50'])}")
    return 0


def cmd_report(args) -> int:
    from tracker.evaluation.report import build_report
    path = build_report(args.model, args.data, args.out, ablate_json=args.ablate, reuse=args.reuse,
                        max_frames=args.max_frames, log=lambda m: print(m, file=sys.stderr))
    print(f"wrote {path} (with its PNG plots and evaluation JSONs beside it)")
    return 0


def _para(text: str) -> str:
    import textwrap
    return textwrap.fill(text, 88)


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


def add_commands(sub, REPO) -> None:
    """The user's jobs, each a sub-parser of ``sub``."""
    s = sub.add_parser("demo", help="replay the bundled recording through the pipeline (default)",
                       description=_para("The bundled recording (demo/lmo_dev: 50 real LM-O frames as a video, with "
                                   "their ground truth) through the whole pipeline with models/lmo: detector, "
                                   "crops, encoder, regressors, overlay, rerun; accuracy against the ground truth."),
                       epilog=RUN_FOLDER_HELP + "\nexamples:\n  python app.py demo\n"
                              "  python app.py demo --video-out demo.mp4\n"
                              "  python app.py demo --rerun serve          # then open the printed URL\n",
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    s.add_argument("--out", help="run folder (default runs/demo-TIMESTAMP)")
    s.add_argument("--max-frames", type=positive_int, default=None, metavar="N", help="stop after N frames")
    add_output_options(s, rerun_default="save")
    s.set_defaults(func=cmd_demo)

    s = sub.add_parser("track", help="the frame loop on a camera, video, image folder or BOP scene",
                       description=_para("Track a bundle's objects in a camera's frames (V4L2 index or /dev/videoN), "
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
    s.add_argument("--smooth", type=float, default=None, metavar="ALPHA",
                   help="temporal smoothing on SO(3) x R^3, 0 < ALPHA <= 1 (smaller = smoother); off by default")
    s.add_argument("--boxes", choices=["auto", "gt", "detector"], default="auto",
                   help="auto: ground truth on BOP scenes that have it, else the bundle's detector")
    add_output_options(s, rerun_default="save")
    s.set_defaults(func=cmd_track)

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

    s = sub.add_parser("calibrate", help="checkerboard calibration -> camera file")
    g = s.add_mutually_exclusive_group()
    g.add_argument("--images", help="glob of board photos, e.g. 'calib/*.jpg'")
    g.add_argument("--source", help="video file or camera index")
    s.add_argument("--board", required=True, help="inner corners COLSxROWS, e.g. 9x6")
    s.add_argument("--square", type=positive_float, required=True, help="square side in mm")
    s.add_argument("--out", required=True, help="camera file to write (OpenCV YAML)")
    s.add_argument("--every", type=positive_int, default=15, help="with --source: use every Nth frame")
    s.set_defaults(func=cmd_calibrate)

    s = sub.add_parser("imu", help="compare tracked rotations with an IMU fixed to the object")
    s.add_argument("--run", required=True, help="a 'track' run folder (poses.csv, timings.csv)")
    s.add_argument("--imu", required=True, help="IMU log CSV: t,qw,qx,qy,qz[,gx,gy,gz]")
    s.add_argument("--out", required=True, help="folder for imu_report.json and the plots")
    s.add_argument("--obj-id", type=int, help="the tracked object carrying the IMU")
    s.add_argument("--mode", choices=["full", "simple"], default="full",
                   help="full: estimate clock offset, mounting and world rotations; simple: the "
                        "thesis's relative-to-first-sample comparison")
    s.add_argument("--max-gap", type=positive_float, default=0.25, help="never interpolate across IMU gaps longer (s)")
    s.add_argument("--time-offset", type=finite_float, default=None, metavar="S",
                   help="IMU clock minus camera clock in seconds (default: estimated from the angular speeds)")
    s.add_argument("--max-offset", type=positive_float, default=2.0, metavar="S",
                   help="search the clock offset within +- S seconds (default 2)")
    s.set_defaults(func=cmd_imu)

    s = sub.add_parser("eval", help="run a bundle on a BOP scene and score it")
    s.add_argument("--model", required=True, help="model bundle folder")
    s.add_argument("--data", required=True, help="BOP scene folder with ground truth")
    s.add_argument("--boxes", choices=["gt", "detector"], default="gt")
    s.add_argument("--mode", choices=["regression", "aae"], default="regression",
                   help="latent regression (the thesis) or the AAE codebook baseline")
    s.add_argument("--json", required=True, help="metrics JSON to write")
    s.add_argument("--bop-csv", help="BOP results CSV (default: METHOD_lmo-test.csv beside the JSON)")
    s.add_argument("--max-frames", type=positive_int)
    s.add_argument("--gt-models", metavar="DIR",
                   help="for a bundle of some of the scene's objects: meshes of all of them (obj_NNNNNN.ply), so "
                        "the others still hide parts of the bundle's (default: BOP's models/ beside or above the "
                        "scene when it has them)")
    s.set_defaults(func=cmd_eval)

    s = sub.add_parser("score", help="score a BOP results CSV against a BOP scene")
    s.add_argument("--results", required=True, help="BOP results CSV")
    s.add_argument("--data", required=True, help="BOP scene folder with ground truth")
    s.add_argument("--models", required=True, help="folder of obj_NNNNNN.ply")
    s.add_argument("--models-info", help="models_info.json (default: the models folder's, else computed)")
    s.add_argument("--json", required=True, help="metrics JSON to write")
    s.set_defaults(func=cmd_score)

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
    s.add_argument("--distractors", choices=["plain", "hard", "household"], default="plain",
                   help="plain: 0-5 random primitives per image (as data made before); hard: 2-8 primitives "
                        "textured from the photos and tinted, half the time with the targets' colours; "
                        "household: as hard, half of the shapes mugs, cups and bottles")
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

    s = sub.add_parser("train", help="autoencoder + latent regressors (+ AAE codebook) -> model bundle")
    s.add_argument("--data", required=True, help="a 'synth' split")
    s.add_argument("--out", required=True, help="bundle folder, e.g. models/lmo")
    s.add_argument("--method", choices=["dalsr", "cvml", "cvam"], default="cvam")
    s.add_argument("--encoder", choices=["plain", "resnet", "lite0", "lite1", "lite2"], default="plain",
                   help="plain strided convs (CVML-base), residual blocks (CVML-18 style), or an ImageNet-pretrained "
                        "EfficientNet-Lite trunk (lite0/1/2, fine-tuned with its BatchNorm frozen; crops a multiple "
                        "of 32 px, e.g. --size 128)")
    s.add_argument("--no-pretrained", action="store_true",
                   help="with --encoder lite*: the same network from random weights, BatchNorm learning (the control)")
    s.add_argument("--lr", type=positive_float, default=1e-3, help="the autoencoder's AdamW learning rate")
    s.add_argument("--batch", type=positive_int, default=128, help="the autoencoder's batch size")
    s.add_argument("--lr-schedule", choices=LR_SCHEDULES, default="plateau",
                   help="the autoencoder's step size: divided by 5 after 3 epochs without a better validation L2 "
                        "(plateau), or annealed by a cosine over --minutes (budget; no better on dev, stop 50)")
    s.add_argument("--head-sets", type=positive_int, default=1, metavar="N",
                   help="pose-head sets fitted with seeds seed, seed+1, ... and averaged, each with --reg-minutes")
    s.add_argument("--kl-warmup", type=nonnegative_int, default=0, metavar="STEPS",
                   help="variational methods: raise the KL term's weight from 0 over this many steps (0: full "
                        "weight from the start)")
    s.add_argument("--device", choices=["auto", "cpu", "cuda"], default="auto",
                   help="where the autoencoder trains: a CUDA GPU where torch sees one (auto), or the CPU")
    s.add_argument("--size", type=positive_int, default=64, help="crop side in pixels (thesis: 128)")
    s.add_argument("--latent", type=positive_int, default=128)
    s.add_argument("--minutes", type=positive_float, default=45.0, help="autoencoder time budget")
    add_regressor_budget(s)
    s.add_argument("--seed", type=nonnegative_int, default=0)
    s.add_argument("--max-images", type=positive_int, help="use only the first N scene images")
    s.add_argument("--models-info", help="models_info.json (default: computed from the meshes)")
    s.add_argument("--init-from", metavar="CKPT",
                   help="start from another run's ae_checkpoint.pt (same network), e.g. to train on more data")
    add_precision(s)
    s.set_defaults(func=cmd_train)

    s = sub.add_parser("train-detector", help="train the 2D detector on synth scenes and add it to a bundle",
                       description="Train the 2D detector on synth scenes and add it to a bundle. Under "
                                   "'torchrun --nproc_per_node N app.py train-detector ...' N processes (GPUs, or "
                                   "CPU processes with gloo) share every batch.")
    s.add_argument("--data", required=True, help="a 'synth' split")
    s.add_argument("--model", required=True, help="the bundle that gets detector.onnx")
    s.add_argument("--minutes", type=positive_float, default=60.0, help="training time budget (cosine schedule over it)")
    s.add_argument("--width", type=positive_int, default=32, help="base channel width of the network")
    s.add_argument("--input", type=positive_int, nargs=2, default=(320, 240), metavar=("W", "H"), help="network input size")
    s.add_argument("--batch", type=positive_int, default=32)
    s.add_argument("--lr", type=positive_float, default=2e-3, help="peak learning rate (lower to fine-tune)")
    s.add_argument("--seed", type=nonnegative_int, default=0)
    s.add_argument("--max-images", type=positive_int, default=None, help="use only the first N images")
    s.add_argument("--init-from", metavar="CKPT|BUNDLE",
                   help="start from another run's detector_ckpt_*.pt (same width and classes), e.g. to fine-tune on "
                        "new data, or from a bundle whose detector is one float network (its weights read back from "
                        "the ONNX graph; its BatchNorms then stay frozen)")
    s.add_argument("--boxes", choices=("visible", "amodal"), default="visible",
                   help="what the boxes cover: the visible part of each object, or its whole silhouette clipped "
                        "to the image (amodal: size and centre follow the object behind occluders)")
    s.add_argument("--occlusion", type=fraction, default=0.0, metavar="P",
                   help="share of training images that get clutter pasted over them (occlusion augmentation)")
    s.add_argument("--paste-objects", type=fraction, default=0.0, metavar="P",
                   help="share of those pasted rectangles cut around another image's object, which then "
                        "becomes a target too (objects in front of objects)")
    s.add_argument("--cutouts", metavar="DIR",
                   help="folder of RGBA images of things cut out of their background (PNG with alpha), "
                        "pasted over training images as real clutter that is not a target (docs/experiments/)")
    s.add_argument("--cutout-share", type=fraction, default=None, metavar="P",
                   help="share of training images that get 1-3 cut-outs pasted over them (with --cutouts; default 0.5)")
    s.add_argument("--colour", choices=("standard", "strong", "mild"), default="standard",
                   help="photometric augmentation: brightness, contrast, saturation, white balance, blur and noise; "
                        "'strong' adds grey-scale blends, per-channel gains and offsets, hue turns, inverted "
                        "channels and wider blurs (as detectors trained on renders for BOP do); 'mild' leaves "
                        "out saturation and white balance (the objects' colours kept)")
    s.add_argument("--ema", type=float, default=0.0, metavar="DECAY",
                   help="validate and export the exponential moving average of the weights with this decay "
                        "(e.g. 0.999: about the last 1,000 steps) instead of the last weights; 0: off")
    s.add_argument("--backbone", choices=["plain", "lite0", "lite1", "lite2"], default="plain",
                   help="plain: the small convolutional backbone from random weights; lite0-2: an ImageNet-pretrained "
                        "EfficientNet-Lite trunk (BatchNorm frozen) under the same neck and heads")
    s.add_argument("--no-pretrained", action="store_true",
                   help="with --backbone lite*: the same network from random weights, BatchNorm learning (the control)")
    s.add_argument("--device", choices=["auto", "cpu", "cuda"], default="auto",
                   help="where the detector trains: a CUDA GPU where torch sees one (auto), or the CPU")
    add_precision(s)
    s.set_defaults(func=cmd_train_detector)

    s = sub.add_parser("build", help="your meshes -> a finished tracking bundle, in one time budget (resumable)",
                       description=_para("From a folder of meshes (PLY, OBJ, STL, GLB) to a bundle: the meshes in "
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
    s.add_argument("--detector-backbone", choices=["plain", "lite0", "lite1", "lite2"], default="plain")
    s.add_argument("--workers", type=positive_int, default=2, help="render processes")
    s.add_argument("--mesh-faces", type=nonnegative_int, default=SYNTH_FACES, metavar="N",
                   help=f"render the objects decimated to about N faces (default {SYNTH_FACES}; 0: the full meshes)")
    s.add_argument("--device", choices=["auto", "cpu", "cuda"], default="auto",
                   help="where the networks train: a CUDA GPU where torch sees one (auto), or the CPU")
    s.add_argument("--head-sets", type=positive_int, default=3, metavar="N",
                   help="pose-head sets fitted with seeds seed, seed+1, ... and averaged (default 3; 1: the recipe "
                        "before stop 51)")
    s.add_argument("--max-images", type=positive_int, metavar="N",
                   help="the most images per rendered split (default: what this machine's memory can train on)")
    s.add_argument("--from-manifest", metavar="BUNDLE", help="redo the recipe a built bundle records (its options)")
    s.set_defaults(func=cmd_build)

    s = sub.add_parser("report", help="reproduction report: our numbers next to the thesis's (Markdown + PNG)")
    s.add_argument("--model", default=str(REPO / "models" / "lmo"))
    s.add_argument("--data", default=None, help="BOP scene with ground truth (default: the bundled recording)")
    s.add_argument("--out", required=True, help="report folder")
    s.add_argument("--ablate", help="JSON written by 'app.py lab ablate' (Tables 4.1 / 4.2)")
    s.add_argument("--reuse", action="store_true", help="reuse evaluation JSONs already in --out")
    s.add_argument("--max-frames", type=positive_int)
    s.set_defaults(func=cmd_report)
