"""``build``'s one-page report, written into the bundle (``report/``, hashed like its other
files): what was built, how well it does on held-out renders, and how long each stage took."""
from __future__ import annotations

from dataclasses import asdict
from pathlib import Path


def _f(v, nd=3) -> str:
    return "n/a" if v is None else f"{v:.{nd}f}"


def write_build_report(folder, work_root, stages: dict, recipe, planned: dict, names: dict) -> Path:
    """``folder``: the (staged) bundle; ``work_root``: the build's work folder (its splits and
    the held-out check's metrics); ``stages``: the build state. Returns report.md's path."""
    from tracker.training.synth.preview import preview
    rep = Path(folder) / "report"
    rep.mkdir(parents=True, exist_ok=True)
    preview(Path(work_root) / "split_encoder", rep / "samples.png", n_scenes=6, n_crops=12)
    check = stages.get("check", {})
    lines = ["# Build report", "",
             f"Made by `app.py build --models {recipe.models} --minutes {recipe.minutes:g}` "
             f"(prior `{recipe.prior}`, encoder `{recipe.encoder}` {recipe.size} px, detector `{recipe.detector_backbone}` "
             f"{recipe.detector_input[0]} x {recipe.detector_input[1]}{' int8' if recipe.detector_int8 else ''}, seed {recipe.seed}). Objects: " + ", ".join(f"{k} {v}" for k, v in sorted(names.items(), key=lambda x: int(x[0]))) + ".",
             "", "## On held-out renders", "",
             f"{planned['check_images']} fresh synthetic images (seed {recipe.seed + 1000}), never trained on. "
             "Renders flatter the tracker: real frames score lower (docs/models.md).", "",
             "| boxes | ADD(I) | AR_MSSD | AR_MSPD | RE median | TE median | detector AP50 | ms per image |",
             "|---|---|---|---|---|---|---|---|"]
    for boxes in ("gt", "detector"):
        m = check.get(boxes, {})
        lines.append(f"| {'ground truth' if boxes == 'gt' else 'detector'} | {_f(m.get('add_recall'))} | "
                     f"{_f(m.get('ar_mssd'))} | {_f(m.get('ar_mspd'))} | {_f(m.get('re_median_deg'), 1)} deg | "
                     f"{_f(m.get('te_median_mm'), 1)} mm | {_f(m.get('ap50')) if boxes == 'detector' else ''} | "
                     f"{_f(m.get('ms_per_image'), 1)} |")
    lines += ["", "Per object (detector boxes): ADD(I) / AR_MSSD / AR_MSPD, instances", "",
              "| object | ADD(I) | AR_MSSD | AR_MSPD | instances |", "|---|---|---|---|---|"]
    for o, v in sorted(check.get("detector", {}).get("per_object", {}).items(), key=lambda x: int(x[0])):
        lines.append(f"| {names.get(str(o), o)} | {_f(v.get('add_recall'))} | {_f(v.get('ar_mssd'))} | "
                     f"{_f(v.get('ar_mspd'))} | {v.get('n_gt')} |")
    lines += ["", "## Sample renders and their crops", "", "![samples](samples.png)", "",
              "## Stages", "", "| stage | minutes | planned | result |", "|---|---|---|---|"]
    planned_min = {"render": f"{planned['render_seconds'] / 60:.1f} min", "render-det": f"{planned['render_det_seconds'] / 60:.1f} min",
                   "encoder": f"{planned['encoder_minutes']:g} min + heads", "detector": f"{planned['detector_minutes']:g} min"}
    for name, s in stages.items():
        if name == "report":
            continue
        shown = {k: (round(v, 3) if isinstance(v, float) else v) for k, v in s.items()
                 if k not in ("key", "done", "seconds") and not isinstance(v, dict)}
        lines.append(f"| {name} | {(s.get('seconds') or 0) / 60:.1f} | {planned_min.get(name, '')} | "
                     + ", ".join(f"{k} {v}" for k, v in shown.items()) + " |")
    lines += ["", "Recipe (also in manifest.json, `build`): `" + str(asdict(recipe)) + "`", ""]
    path = rep / "report.md"
    path.write_text("\n".join(lines))
    return path
