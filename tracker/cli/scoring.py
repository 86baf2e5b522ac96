"""The scoring commands: ``eval`` (a bundle on a BOP scene), ``score`` (a BOP results CSV) and
``report`` (the reproduction report)."""
from __future__ import annotations

import sys

from tracker.cli.args import fraction, positive_int


def add_eval(sub, REPO) -> None:
    """``app.py eval``: run a bundle on a BOP scene and score it."""
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
    s.add_argument("--per-instance", metavar="FILE",
                   help="also write a CSV with one row per ground-truth instance: its errors and pass/fail at "
                        "every threshold (the input of 'app.py lab compare')")
    s.add_argument("--candidates", type=positive_int, metavar="K",
                   help="with --boxes detector: pose up to K detector boxes per object and keep the most confident "
                        "(default: the bundle's detector spec, 1 for models/lmo)")
    s.add_argument("--candidate-floor", type=fraction, metavar="S",
                   help="with --candidates: the lowest score a further box may have (default: the spec's, 0.05)")
    s.set_defaults(func=cmd_eval)


def cmd_eval(args) -> int:
    from tracker.evaluation.evaluate import evaluate
    m = evaluate(args.model, args.data, args.json, boxes=args.boxes, mode=args.mode, bop_csv=args.bop_csv,
                 max_frames=args.max_frames, gt_models=args.gt_models, per_instance=args.per_instance,
                 candidates_per_object=args.candidates, candidate_floor=args.candidate_floor)
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
        side = {int(k): v for k, v in d.get("box_errors", {}).get("per_object", {}).items()}
        print(f"{'obj':>5} {'AP':>6} {'AP50':>6} {'R50':>6} {'side':>7}")
        for k, v in sorted(d["per_object"].items(), key=lambda kv: int(kv[0])):
            if v["n_gt"]:
                s = side.get(int(k), {}).get("side_log_ratio_mean")
                print(f"{k:>5} {fmt_num(v['ap']):>6} {fmt_num(v['ap50']):>6} {fmt_num(v['recall50']):>6} "
                      f"{'-' if s is None else f'{s:+.3f}':>7}")
        if side:
            print("side: mean log ratio of the run-time boxes' longer side to the truth's, where they overlap it "
                  "by IoU >= 0.5 (below 0: too short; the depth follows it)")
    print(f"visibility: {m['visibility_source']}\nwrote {args.json} and {m['bop_csv']}"
          + (f" and {args.per_instance}" if args.per_instance else ""))
    return 0


def add_score(sub, REPO) -> None:
    """``app.py score``: score a BOP results CSV against a BOP scene."""
    s = sub.add_parser("score", help="score a BOP results CSV against a BOP scene")
    s.add_argument("--results", required=True, help="BOP results CSV")
    s.add_argument("--data", required=True, help="BOP scene folder with ground truth")
    s.add_argument("--models", required=True, help="folder of obj_NNNNNN.ply")
    s.add_argument("--models-info", help="models_info.json (default: the models folder's, else computed)")
    s.add_argument("--json", required=True, help="metrics JSON to write")
    s.add_argument("--per-instance", metavar="FILE",
                   help="also write a CSV with one row per ground-truth instance, as 'eval --per-instance' does "
                        "(e.g. for a 'track' run's poses.csv; the input of 'app.py lab compare')")
    s.set_defaults(func=cmd_score)


def cmd_score(args) -> int:
    from tracker.core.bop import check_output_file
    from tracker.evaluation.scoring import score_results, write_metrics_json
    check_output_file(args.json, "--json")
    if args.per_instance:
        check_output_file(args.per_instance, "--per-instance")
    records = []
    m = score_results(args.results, args.data, args.models, models_info=args.models_info, records_out=records)
    write_metrics_json(args.json, m)
    if args.per_instance:
        from tracker.evaluation.scoring import per_instance_rows, write_per_instance
        write_per_instance(args.per_instance, per_instance_rows(records))
    from tracker.evaluation.report import fmt_num  # (no instances: the recalls are null)
    print(f"{m['n_gt']} ground-truth instances, {m['n_est']} estimates: ADD(I) {fmt_num(m['add_recall'])}, "
          f"AR_MSSD {fmt_num(m['ar_mssd'])}, AR_MSPD {fmt_num(m['ar_mspd'])}, AR {fmt_num(m['ar'])} "
          f"(visibility: {m['visibility_source']})")
    print(f"wrote {args.json}" + (f" and {args.per_instance}" if args.per_instance else ""))
    return 0


def add_report(sub, REPO) -> None:
    """``app.py report``: our numbers next to the thesis's."""
    s = sub.add_parser("report", help="reproduction report: our numbers next to the thesis's (Markdown + PNG)")
    s.add_argument("--model", default=str(REPO / "models" / "lmo"))
    s.add_argument("--data", default=None, help="BOP scene with ground truth (default: the bundled recording)")
    s.add_argument("--out", required=True, help="report folder")
    s.add_argument("--ablate", help="JSON written by 'app.py lab ablate' (Tables 4.1 / 4.2)")
    s.add_argument("--reuse", action="store_true", help="reuse evaluation JSONs already in --out")
    s.add_argument("--max-frames", type=positive_int)
    s.set_defaults(func=cmd_report)


def cmd_report(args) -> int:
    from tracker.evaluation.report import build_report
    path = build_report(args.model, args.data, args.out, ablate_json=args.ablate, reuse=args.reuse,
                        max_frames=args.max_frames, log=lambda m: print(m, file=sys.stderr))
    print(f"wrote {path} (with its PNG plots and evaluation JSONs beside it)")
    return 0
