"""``app.py report``: our numbers next to the thesis's, as Markdown plus PNG plots.

- Table 5.6: the AAE codebook (LUT) against latent regression, ground-truth boxes.
- Table 5.7: ground-truth against detector boxes (and the detector's AP).
- Figure 5.3: recall against visibility.
- Tables 4.1 / 4.2: the regressor ablations (from ``app.py lab ablate``'s JSON).
- Figure 4.13: t-SNE of the latent codes of the scene's crops, coloured by object and by genus.

The evaluations are run here (``evaluate``), one JSON each in the output folder.
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from tracker.core.errors import UserError

# the thesis's figures (../shared/METHOD.md)
THESIS = {
    "table_5_3": {"AAE": {"ar_mssd": 0.095, "ar_mspd": 0.254}, "CVML-Pose": {"ar_mssd": 0.347, "ar_mspd": 0.714},
                  "CVAM-Pose": {"ar_mssd": 0.318, "ar_mspd": 0.709}},
    "table_5_6": {"aae": {"ar_mspd": 0.666}, "regression": {"ar_mspd": 0.709}},
    "table_5_7": {"gt": {"add_recall": 0.2800}, "detector": {"add_recall": 0.2097}},
    "table_4_1": {"MLP + 6D": 0.913, "MLP + quaternion": 0.901, "NNS (codebook, cosine)": 0.876, "RF + 6D": 0.867,
                  "MLP + axis-angle": 0.858},
    "table_4_2a": {"MLP": 1.61, "box centre": 4.03},
    "table_4_2b": {"KNN": 25.9, "RF": 31.6, "MLP": 36.2},
}


def fmt_num(v, nd=3):
    """A number for a table or a log line; None prints as a dash."""
    return "-" if v is None else f"{v:.{nd}f}"


def _pose_row(label, m, thesis=None):
    return (f"| {label} | {m['n_gt']} | {fmt_num(m['add_recall'])} | {fmt_num(m['ar_mssd'])} | {fmt_num(m['ar_mspd'])} | "
            f"{fmt_num(m['re_median_deg'], 1)} | {fmt_num(m['te_median_mm'], 1)} | {thesis or ''} |")


POSE_HEAD = ("| | instances | ADD(I) | AR_MSSD | AR_MSPD | RE median (deg) | TE median (mm) | thesis |\n"
             "|---|---|---|---|---|---|---|---|")


def latent_tsne(model_dir, scene_dir, seed: int = 0, max_frames=None):
    """t-SNE (2D) of the encoder's latent means for the scene's ground-truth crops (>= 10 %
    visible): (xy, obj_ids)."""
    from sklearn.manifold import TSNE

    from tracker.core.bop import load_scene
    from tracker.runtime.estimator import Detection, PoseEstimator
    from tracker.evaluation.evaluate import gt_boxes, gt_instances_with_boxes
    from tracker.core.meshes import load_models
    est = PoseEstimator(model_dir)
    scene = load_scene(scene_dir, require_gt=True)
    ids = scene.im_ids[:max_frames] if max_frames else scene.im_ids
    models = load_models(est.bundle.root / "meshes", sorted({g.obj_id for i in ids for g in scene.gt[i]}))
    boxes, _ = gt_boxes(scene, models, ids)
    mus, objs = [], []
    for i in ids:
        dets = [Detection(o, b, exact=True) for o, b, _ in gt_instances_with_boxes(scene.gt[i], boxes[i], 0.1)]
        if dets:
            mus.append(est.encode(est.crops(scene.read_rgb(i), [d.box for d in dets]), [d.obj_id for d in dets]))
            objs += [d.obj_id for d in dets]
    mu = np.concatenate(mus)
    perplexity = float(min(30, max(2, (len(mu) - 1) / 3)))
    xy = TSNE(2, perplexity=perplexity, init="pca", random_state=seed).fit_transform(mu)
    return xy, np.array(objs)


ABLATE_KEYS = ("train", "validation", "note", "mlp_minutes", "table_4_1", "table_4_2a", "table_4_2b")


def _read_ablate(path) -> dict:
    p = Path(path)
    if not p.is_file():
        raise UserError(f"--ablate {p}: file not found (write it with 'app.py lab ablate ... --json {p}')")
    try:
        a = json.loads(p.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError):
        raise UserError(f"--ablate {p}: not a JSON file") from None
    missing = [k for k in ABLATE_KEYS if not isinstance(a, dict) or k not in a]
    if missing:
        raise UserError(f"--ablate {p}: not written by 'app.py lab ablate' (missing {', '.join(missing)})")
    return a


def build_report(model_dir, scene_dir, out_dir, ablate_json=None, reuse: bool = False, max_frames=None,
                 log=print) -> Path:
    from tracker.core.bundle import open_bundle
    from tracker.core.cvplot import Panel, Series, line_chart, save_png, scatter
    from tracker.evaluation.evaluate import evaluate
    from tracker.core.meshes import genus, load_mesh
    if scene_dir is None:
        from tracker.core.paths import DEMO_RECORDING
        scene_dir = DEMO_RECORDING
    ablate = _read_ablate(ablate_json) if ablate_json else None  # fail before the long evaluations
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    bundle = open_bundle(model_dir)
    names = {o.id: o.name for o in bundle.objects}
    has_det = bundle.manifest.has_detector
    runs = [("gt", "regression"), ("gt", "aae")] + ([("detector", "regression"), ("detector", "aae")] if has_det else [])
    ev = {}
    bundle_sha = bundle.manifest_sha256  # a JSON made for the bundle before it changed is not reused
    for boxes, mode in runs:
        p = out / f"eval_{boxes}_{mode}.json"
        old = None
        if reuse and p.is_file():
            try:
                old = json.loads(p.read_text())
            except (json.JSONDecodeError, UnicodeDecodeError):
                log(f"warning: {p} is unreadable; evaluating again")
        if old and old.get("data") == str(scene_dir) and old.get("model") == str(model_dir) \
                and old.get("max_frames") == max_frames and old.get("bundle_manifest_sha256") == bundle_sha:
            ev[boxes, mode] = old
        else:
            log(f"evaluating: {boxes} boxes, {mode}")
            ev[boxes, mode] = evaluate(model_dir, scene_dir, p, boxes=boxes, mode=mode, bop_csv=out / f"{boxes}-{mode}.csv",
                                       max_frames=max_frames, progress=False)
    g = ev["gt", "regression"]
    md = [f"# autopose reproduction report: `{model_dir}` on `{scene_dir}`", "",
          f"Generated {time.strftime('%Y-%m-%d %H:%M')}. Bundle: method {bundle.manifest.method}, "
          f"{bundle.manifest.input_size} px crops, latent {bundle.manifest.latent_size}, pose prior "
          f"{bundle.manifest.pose_prior}. Trained on synthetic renders only.", "",
          f"**Visibility**: {g['visibility_source']} (no depth images here, so no VSD: AR = mean of AR_MSSD and "
          f"AR_MSPD). The thesis's numbers are on all 200 LM-O test frames with photorealistic training data and "
          f"a GPU; ours are on the frames of this scene only.", ""]

    md += ["## Table 5.6: AAE codebook (LUT) vs latent regression (ground-truth boxes)", "", POSE_HEAD,
           _pose_row("AAE codebook (LUT)", ev["gt", "aae"], f"AR_MSPD {THESIS['table_5_6']['aae']['ar_mspd']}"),
           _pose_row("latent regression", g, f"AR_MSPD {THESIS['table_5_6']['regression']['ar_mspd']}"), "",
           "Thesis, Table 5.3 (LM-O, detector boxes): AAE AR_MSSD 0.095 / AR_MSPD 0.254; CVAM-Pose 0.318 / 0.709.", ""]

    md += ["## Table 5.7: ground-truth vs detector boxes", ""]
    if has_det:
        d = ev["detector", "regression"]
        md += [POSE_HEAD,
               _pose_row("ground-truth boxes", g, f"ADD(I) {THESIS['table_5_7']['gt']['add_recall']:.3f}"),
               _pose_row("our detector", d, f"ADD(I) {THESIS['table_5_7']['detector']['add_recall']:.3f} (Mask R-CNN)"),
               _pose_row("our detector, AAE", ev["detector", "aae"], "AR_MSPD 0.254 (Table 5.3)"), ""]
        det = d["detection"]
        op = det["operating_point"]  # reused JSONs are of this bundle, made with it
        md += [f"Detector on these frames (COCO's protocol, ranked candidates): AP {fmt_num(det['ap'])}, AP50 "
               f"{fmt_num(det['ap50'])}, recall at IoU 0.5 {fmt_num(det['recall50'])}; the detections the poses "
               f"use (one per object above the manifest's threshold): AP {fmt_num(op['ap'])}, AP50 "
               f"{fmt_num(op['ap50'])}, recall {fmt_num(op['recall50'])}; {det['ms_per_image_median']:.1f} ms "
               f"per frame (median, 2 threads). Thesis: Mask R-CNN AP 0.566 (IoU .5:.95).", "",
               "| object | AP | AP50 | recall50 | instances |", "|---|---|---|---|---|"]
        md += [f"| {names.get(int(k), k)} | {fmt_num(v['ap'])} | {fmt_num(v['ap50'])} | {fmt_num(v['recall50'])} | {v['n_gt']} |"
               for k, v in sorted(det["per_object"].items(), key=lambda kv: int(kv[0])) if v["n_gt"]]
        md.append("")
    else:
        md += ["The bundle has no detector: only ground-truth boxes.", ""]

    md += ["## Per object (latent regression, ground-truth boxes)", "",
           "| object | ADD(I) | AR_MSSD | AR_MSPD | RE median | TE median |", "|---|---|---|---|---|---|"]
    md += [f"| {names.get(int(k), k)} | {fmt_num(v['add_recall'])} | {fmt_num(v['ar_mssd'])} | {fmt_num(v['ar_mspd'])} | "
           f"{fmt_num(v['re_median_deg'], 1)} | {fmt_num(v['te_median_mm'], 1)} |"
           for k, v in sorted(g["per_object"].items(), key=lambda kv: int(kv[0])) if v.get("n_gt")]
    md.append("")

    # Figure 5.3: recall against visibility
    series = []
    for (boxes, mode), m in ev.items():
        if mode != "regression":
            continue
        bins = [b for b in m["recall_by_visibility"] if b["n_gt"]]
        x = np.array([(b["visib_min"] + b["visib_max"]) / 2 for b in bins])
        series.append(Series(x, np.array([b["ar_mspd"] for b in bins]), f"AR_MSPD, {boxes} boxes"))
        series.append(Series(x, np.array([b["add_recall"] for b in bins]), f"ADD(I), {boxes} boxes"))
    for k, s in enumerate(series):
        s.colour = [(31, 119, 180), (214, 39, 40), (44, 160, 44), (255, 127, 14)][k % 4]
    img = line_chart([Panel(series, title="recall vs visible fraction (Figure 5.3)", xlabel="visible fraction",
                            ylabel="recall", ylim=(0.0, 1.0))])
    save_png(out / "recall_vs_visibility.png", img)
    md += ["## Figure 5.3: recall against visibility", "", "![recall vs visibility](recall_vs_visibility.png)", "",
           "| visible fraction | instances | ADD(I) | AR_MSPD |", "|---|---|---|---|"]
    md += [f"| {b['visib_min']:.1f}-{b['visib_max']:.1f} | {b['n_gt']} | {fmt_num(b['add_recall'])} | {fmt_num(b['ar_mspd'])} |"
           for b in g["recall_by_visibility"]]
    md += ["", "Series, top to bottom in the legend order: " + ", ".join(s.label for s in series) + ".", ""]

    # Tables 4.1 / 4.2
    md += ["## Tables 4.1 and 4.2: regressor ablations (synthetic validation split)", ""]
    if ablate is not None:
        a = ablate
        md += [f"From `{ablate_json}`: {a['train']} training / {a['validation']} validation crops, "
               f"{a['note']}; each MLP trained for at most {a['mlp_minutes']} min.", "",
               "**Table 4.1, rotation** (ADD(I) with the true translation)", "",
               "| regressor | ADD(I) | RE median (deg) | thesis ADD(I) |", "|---|---|---|---|"]
        md += [f"| {r['method']} | {fmt_num(r['add_recall_true_t'])} | {fmt_num(r['re_median_deg'], 1)} | "
               f"{fmt_num(THESIS['table_4_1'].get(r['method']))} |" for r in a["table_4_1"]]
        md += ["", "**Table 4.2a, centre**", "", "| regressor | mean error (px) | median (px) | thesis (px) |",
               "|---|---|---|---|"]
        md += [f"| {r['method']} | {fmt_num(r['centre_err_mean_px'], 2)} | {fmt_num(r['centre_err_median_px'], 2)} | "
               f"{fmt_num(THESIS['table_4_2a'].get(r['method']), 2)} |" for r in a["table_4_2a"]]
        md += ["", "**Table 4.2b, distance**", "", "| regressor | mean abs Tz error (mm) | median (mm) | thesis (mm) |",
               "|---|---|---|---|"]
        md += [f"| {r['method']} | {fmt_num(r['tz_err_mean_mm'], 1)} | {fmt_num(r['tz_err_median_mm'], 1)} | "
               f"{fmt_num(THESIS['table_4_2b'].get(r['method']), 1)} |" for r in a["table_4_2b"]]
        md.append("")
    else:
        md += ["Not run: pass `--ablate FILE` from `app.py lab ablate`.", ""]

    # t-SNE
    xy, objs = latent_tsne(model_dir, scene_dir, max_frames=max_frames)
    gen = {o.id: genus(load_mesh(bundle.root / o.mesh, o.id).mesh) for o in bundle.objects}
    save_png(out / "tsne_objects.png", scatter(xy, objs, names, "t-SNE of latent codes, by object"))
    save_png(out / "tsne_genus.png", scatter(xy, np.array([gen[o] for o in objs]),
                                             {g_: f"genus {g_}" for g_ in set(gen.values())},
                                             "t-SNE of latent codes, by genus"))
    md += ["## Figure 4.13: t-SNE of the latent space", "",
           f"{len(objs)} crops of this scene (ground-truth boxes). Genus from each mesh's Euler characteristic: "
           + ", ".join(f"{names[o]} {gen[o]}" for o in sorted(gen)) + ".", "",
           "![by object](tsne_objects.png) ![by genus](tsne_genus.png)", ""]
    path = out / "report.md"
    path.write_text("\n".join(md))
    return path
