"""The camera's commands: ``calibrate`` (a checkerboard -> a camera file) and ``imu`` (tracked
rotations against an IMU fixed to the object)."""
from __future__ import annotations

import sys

from tracker.cli.args import finite_float, positive_float, positive_int
from tracker.core.errors import UserError


def add_calibrate(sub, REPO) -> None:
    """``app.py calibrate``: checkerboard calibration -> camera file."""
    s = sub.add_parser("calibrate", help="checkerboard calibration -> camera file")
    g = s.add_mutually_exclusive_group()
    g.add_argument("--images", help="glob of board photos, e.g. 'calib/*.jpg'")
    g.add_argument("--source", help="video file or camera index")
    s.add_argument("--board", required=True, help="inner corners COLSxROWS, e.g. 9x6")
    s.add_argument("--square", type=positive_float, required=True, help="square side in mm")
    s.add_argument("--out", required=True, help="camera file to write (OpenCV YAML)")
    s.add_argument("--every", type=positive_int, default=15, help="with --source: use every Nth frame")
    s.set_defaults(func=cmd_calibrate)


def cmd_calibrate(args) -> int:
    from tracker.core.calibration import calibrate, parse_board
    from tracker.core.camera import camera_file_problem, write_camera
    if not args.images and args.source is None:
        raise UserError("calibrate needs --images GLOB or --source SRC")
    board = parse_board(args.board)
    problem = camera_file_problem(args.out)  # before the work
    if problem:
        raise UserError(f"--out {problem}")
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


def add_imu(sub, REPO) -> None:
    """``app.py imu``: tracked rotations against an IMU fixed to the object."""
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
