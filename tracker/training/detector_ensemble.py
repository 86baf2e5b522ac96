"""``app.py lab join-detectors``: one ``detector.onnx`` whose output is the mean of the outputs of
several detectors trained apart (``train-detector``), optionally quantised to int8 so that it
runs in about the time of one float network; ``build`` stores its one network int8 with it.
The run-time contract does not change: one input, one (1, C + 4, h, w) output, decoded by
:mod:`tracker.runtime.detector`. Needs ``onnx`` (the training extra), never torch."""
from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from tracker.core.bundle import bundle_writer, sha256
from tracker.runtime.detector import DetectorSpec, bundle_with_detector, float_detector, letterbox, normalise, run_graph
from tracker.core.errors import UserError
from tracker.core.manifest import Manifest

# what every member must share for one letterbox and one decoder to serve all (a member of another
# normalisation gets its own from the shared input: input_affine)
CONTRACT = ("classes", "input_w", "input_h", "stride", "pad_value", "boxes")
CALIBRATION_IMAGES = 200


def _onnx():
    try:
        import onnx
    except ImportError:
        raise UserError("join-detectors needs the 'train' extra (onnx): .venv/bin/pip install -e '.[train]'") from None
    return onnx


MIRROR_MODES = ("none", "both", "alternate")


def member_views(n: int, mirror: str) -> list[tuple[str, ...]]:
    """What each of ``n`` members sees: ``none``, the image; ``both``, the image and its mirror
    image (twice the work); ``alternate``, the image and the mirror image by turns (the first
    member the image), so that members trained alike err less alike at no extra work."""
    if mirror not in MIRROR_MODES:
        raise UserError(f"--mirror must be one of {', '.join(MIRROR_MODES)}, not '{mirror}'")
    if mirror == "both":
        return [("plain", "mirror")] * n
    if mirror == "alternate":
        return [("plain",) if i % 2 == 0 else ("mirror",) for i in range(n)]
    return [("plain",)] * n


def input_affine(spec: DetectorSpec, first: DetectorSpec) -> tuple[float, float] | None:
    """(a, b) such that a member normalised by ``spec`` gets its own input as ``a * x + b`` from
    ``x``, the input normalised by the ensemble's (the first member's) ``first``:
    (rgb - m) / s = x * (s0 / s) + (m0 - m) / s. None when the two normalisations are the same."""
    if (spec.mean, spec.std) == (first.mean, first.std):
        return None
    return first.std / spec.std, (first.mean - spec.mean) / spec.std


def merge_graphs(paths, out_path, mirror: str = "none", affine: list | None = None) -> None:
    """One ONNX graph: the members side by side on one shared input, their outputs averaged
    (``Mean``) into one output named as the first member's. The batch is fixed at 1 (the
    run-time detector sees one frame at a time), which lets onnxruntime fold the shape
    arithmetic of the upsampling away (measured: 6.4 against 6.8 ms for three int8 members).
    ``mirror`` (``member_views``): members that see the image mirrored left to right (with
    ``both``, as a batch of 2 with the image) have that output mirrored back and its x offsets
    turned (``mirror_fix``) before the mean. ``affine``: per member None or (a, b) of
    :func:`input_affine`: that member takes ``a * input + b`` (its own normalisation)."""
    onnx = _onnx()
    from onnx import compose, helper, numpy_helper
    models = [onnx.load(str(p)) for p in paths]
    views = member_views(len(models), mirror)
    first = models[0].graph
    in_name, out_name = first.input[0].name, first.output[0].name
    opset = max(o.version for m in models for o in m.opset_import if o.domain in ("", "ai.onnx"))
    nodes, inits, outs = [], [], []
    flip = ["mirror_starts", "mirror_ends", "mirror_axes", "mirror_steps"]  # Slice: axis 3 backwards
    if any("mirror" in v for v in views):
        channels = first.output[0].type.tensor_type.shape.dim[1].dim_value
        if channels < 5:
            raise UserError(f"{paths[0]}: its output's channel count is not static; re-export the detector")
        scale, shift = mirror_fix(channels)
        inits += [numpy_helper.from_array(np.array(v, np.int64), n) for v, n in
                  zip(([-1], [np.iinfo(np.int64).min], [3], [-1], [1, 1]), flip + ["mirror_split"])]
        inits += [numpy_helper.from_array(scale, "mirror_scale"), numpy_helper.from_array(shift, "mirror_shift")]
        nodes.append(helper.make_node("Slice", [in_name] + flip, ["mirror_input"], name="mirror_input"))
        if any(len(v) == 2 for v in views):
            nodes.append(helper.make_node("Concat", [in_name, "mirror_input"], ["mirror_batch"], axis=0,
                                          name="mirror_batch"))
    feeds = {("plain",): in_name, ("mirror",): "mirror_input", ("plain", "mirror"): "mirror_batch"}
    for i, (m, view) in enumerate(zip(models, views)):
        if len(m.graph.input) != 1 or len(m.graph.output) != 1:
            raise UserError(f"{paths[i]}: a detector has one input and one output")
        m = compose.add_prefix(m, f"m{i}_")
        g = m.graph
        mine = g.input[0].name
        feed = feeds[view]
        if affine and affine[i] is not None:  # the member's own normalisation of the shared input
            a, b = affine[i]
            inits += [numpy_helper.from_array(np.array(a, np.float32), f"m{i}_norm_a"),
                      numpy_helper.from_array(np.array(b, np.float32), f"m{i}_norm_b")]
            nodes += [helper.make_node("Mul", [feed, f"m{i}_norm_a"], [f"m{i}_norm_scaled"], name=f"m{i}_norm_scaled"),
                      helper.make_node("Add", [f"m{i}_norm_scaled", f"m{i}_norm_b"], [f"m{i}_norm_in"],
                                       name=f"m{i}_norm_in")]
            feed = f"m{i}_norm_in"
        for n in g.node:
            for k, name in enumerate(n.input):
                if name == mine:
                    n.input[k] = feed
        nodes += g.node
        inits += g.initializer
        o, p = g.output[0].name, f"m{i}_mirror_"
        if view == ("plain",):
            outs.append(o)
            continue
        if view == ("plain", "mirror"):
            nodes.append(helper.make_node("Split", [o, "mirror_split"], [p + "plain", p + "out"], axis=0, name=p + "split"))
            outs.append(p + "plain")
            o = p + "out"
        nodes += [helper.make_node("Slice", [o] + flip, [p + "back"], name=p + "back"),
                  helper.make_node("Mul", [p + "back", "mirror_scale"], [p + "scaled"], name=p + "scaled"),
                  helper.make_node("Add", [p + "scaled", "mirror_shift"], [p + "fixed"], name=p + "fixed")]
        outs.append(p + "fixed")
    nodes.append(helper.make_node("Mean", outs, [out_name], name="ensemble_mean"))
    io = [onnx.ValueInfoProto(), onnx.ValueInfoProto()]
    for v, src in zip(io, (first.input[0], first.output[0])):
        v.CopyFrom(src)
        v.type.tensor_type.shape.dim[0].Clear()
        v.type.tensor_type.shape.dim[0].dim_value = 1
    graph = helper.make_graph(nodes, "detector_ensemble", [io[0]], [io[1]], inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", opset)],
                              producer_name="autopose join-detectors")
    model.ir_version = models[0].ir_version
    onnx.checker.check_model(model)
    onnx.save(model, str(out_path))


def mirror_fix(channels: int) -> tuple[np.ndarray, np.ndarray]:
    """(scale, shift), each (1, channels, 1, 1): what turns a mirrored image's output, once
    mirrored back, into the plain image's. Heatmaps and log sizes stay; the x offset within the
    cell (channel C + 2 of :func:`tracker.runtime.detector.decode`) becomes 1 - offset: cell j of the
    mirrored back map is cell w - 1 - j of the mirrored image, whose centre x = (j' + o) * stride
    lies at width - x in the plain one, i.e. at (j + 1 - o) * stride."""
    scale = np.ones((1, channels, 1, 1), np.float32)
    shift = np.zeros((1, channels, 1, 1), np.float32)
    scale[0, channels - 2] = -1.0
    shift[0, channels - 2] = 1.0
    return scale, shift


def calibration_inputs(split_dir, spec: DetectorSpec, n: int = CALIBRATION_IMAGES) -> np.ndarray:
    """``n`` images spread evenly over a ``synth`` split, letterboxed and normalised as at run
    time: (n, 3, H, W) float32. Synthetic renders only, never the evaluation frames."""
    from tracker.core.bop import load_scene
    from tracker.training.crops import split_scene_dirs
    scenes = [load_scene(s) for s in split_scene_dirs(split_dir)]
    frames = [(s, i) for s in scenes for i in s.im_ids]
    if not frames:
        raise UserError(f"{split_dir}: no images to calibrate the int8 detector on")
    pick = np.unique(np.linspace(0, len(frames) - 1, min(n, len(frames))).round().astype(int))
    out = []
    for j in pick:
        s, i = frames[j]
        img, _ = letterbox(s.read_rgb(i), spec.input_w, spec.input_h, spec.pad_value)
        out.append(normalise(img[None], spec)[0])
    return np.stack(out)


WEIGHT_BITS = (7, 8)


def _check_bits(weight_bits: int) -> None:
    if weight_bits not in WEIGHT_BITS:
        raise UserError(f"--weight-bits must be 7 or 8, not {weight_bits}")


def quant_method(weight_bits: int) -> str:
    bits = " in 7 bits (reduce_range)" if weight_bits == 7 else ""
    return f"onnxruntime quantize_static: QDQ, per-channel int8 weights{bits}, uint8 activations, min-max"


def quantise(float_path, out_path, inputs: np.ndarray, weight_bits: int = 8) -> None:
    """Static int8 quantisation (QDQ, per-channel int8 weights, uint8 activations, min-max
    ranges over ``inputs``) with onnxruntime's tools. ``weight_bits`` 7 (``reduce_range``):
    the weights use 7 of the 8 bits, so that a CPU without 8-bit dot products cannot saturate
    (AVX2 adds pairs of uint8 x int8 products in int16: 2 x 255 x 127 overflows it, 2 x 255 x 64
    does not; docs/experiments/stop-53.md)."""
    _check_bits(weight_bits)
    from onnxruntime.quantization import CalibrationDataReader, CalibrationMethod, QuantFormat, QuantType, quantize_static
    from onnxruntime.quantization.shape_inference import quant_pre_process
    name = _onnx().load(str(float_path)).graph.input[0].name

    class Reader(CalibrationDataReader):
        def __init__(self):
            self.it = iter(inputs)

        def get_next(self):
            x = next(self.it, None)
            return None if x is None else {name: x[None]}

    with tempfile.TemporaryDirectory() as tmp:
        pre = Path(tmp) / "pre.onnx"
        quant_pre_process(str(float_path), str(pre))
        quantize_static(str(pre), str(out_path), Reader(), quant_format=QuantFormat.QDQ, per_channel=True,
                        reduce_range=weight_bits == 7, activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8,
                        calibrate_method=CalibrationMethod.MinMax)


def half_weights(float_path, out_path, min_size: int = 64) -> int:
    """The float32 graph with its weights (initializers of ``min_size`` values or more) stored
    in float16, each cast back to float32 by a Cast node that onnxruntime folds away when it
    loads the graph: half the file, float32 arithmetic (no int8 path whose sums differ between
    CPUs; float32 kernels still differ in the last bits), weights rounded to float16. Returns
    how many tensors were halved."""
    onnx = _onnx()
    from onnx import TensorProto, helper, numpy_helper
    model = onnx.load(str(float_path))
    g = model.graph
    kept, casts = [], []
    for t in g.initializer:
        a = numpy_helper.to_array(t)
        if a.dtype != np.float32 or a.size < min_size:
            kept.append(t)
            continue
        h = a.astype(np.float16)
        if not np.isfinite(h).all():
            raise UserError(f"{float_path}: weight {t.name} does not fit float16; keep the float32 graph")
        kept.append(numpy_helper.from_array(h, t.name + "_fp16"))
        casts.append(helper.make_node("Cast", [t.name + "_fp16"], [t.name], to=TensorProto.FLOAT, name=t.name + "_cast"))
    nodes = casts + list(g.node)
    del g.initializer[:]
    g.initializer.extend(kept)
    del g.node[:]
    g.node.extend(nodes)
    onnx.checker.check_model(model)
    onnx.save(model, str(out_path))
    return len(casts)


def dequantise_graph(int8_path, out_path) -> dict:
    """The float32 graph of an int8 QDQ detector (as :func:`quantise` writes them): every
    quantised initializer replaced by its exact float value ``(q - zero_point) * scale``, and
    every activation's QuantizeLinear / DequantizeLinear pair by a Clip to the range its uint8
    codes cover (the quantiser folds a ReLU into that range, so the Clip is where it lives
    now). The result computes what the int8 graph computes, without rounding the activations
    to 256 levels: the starting point for quantising again (:func:`requantise_detector`).
    Returns counts of what changed."""
    onnx = _onnx()
    from onnx import helper, numpy_helper
    model = onnx.load(str(int8_path))
    g = model.graph
    inits = {t.name: numpy_helper.to_array(t) for t in g.initializer}

    def axis_shaped(scale, zp, x, axis):
        if scale.ndim == 0:
            return scale, zp
        shape = [1] * x.ndim
        shape[axis] = -1
        return scale.reshape(shape), zp.reshape(shape)

    nodes, new_inits = [], {}
    producers = {o: n for n in g.node for o in n.output}
    weights = clips = 0
    not_qdq = UserError(f"{int8_path}: not an int8 QDQ graph of the kind 'join-detectors --int8' writes")
    for n in g.node:
        if n.op_type in ("QuantizeLinear", "DequantizeLinear") and not all(i in inits for i in n.input[1:] if i):
            raise not_qdq  # scales and zero points computed in the graph
        if n.op_type == "DequantizeLinear" and n.input[0] in inits:
            q = inits[n.input[0]]
            scale = inits[n.input[1]].astype(np.float32)
            zp = inits[n.input[2]] if len(n.input) > 2 and n.input[2] else np.zeros_like(scale, dtype=q.dtype)
            axis = next((a.i for a in n.attribute if a.name == "axis"), 1)
            s, z = axis_shaped(scale, zp, q, axis if axis >= 0 else axis + q.ndim)
            new_inits[n.output[0]] = ((q.astype(np.int64) - z.astype(np.int64)).astype(np.float32) * s).astype(np.float32)
            weights += 1
        elif n.op_type == "DequantizeLinear" and n.input[0] in producers \
                and producers[n.input[0]].op_type == "QuantizeLinear":
            q = producers[n.input[0]]
            scale = float(inits[q.input[1]])
            zp = inits[q.input[2]] if len(q.input) > 2 and q.input[2] else np.zeros((), np.uint8)
            info = np.iinfo(zp.dtype)
            out = n.output[0]
            new_inits[out + "_lo"] = np.array(scale * (info.min - int(zp)), np.float32)
            new_inits[out + "_hi"] = np.array(scale * (info.max - int(zp)), np.float32)
            nodes.append(helper.make_node("Clip", [q.input[0], out + "_lo", out + "_hi"], [out], name=out + "_clip"))
            clips += 1
        elif n.op_type == "QuantizeLinear" and n.input[0] not in inits:
            continue  # its DequantizeLinear became the Clip
        else:
            nodes.append(n)
    if {n.op_type for n in nodes} & {"QuantizeLinear", "DequantizeLinear"} or any(n.domain not in ("", "ai.onnx")
                                                                                  for n in nodes):
        raise not_qdq
    used = {i for n in nodes for i in n.input}
    kept = [t for t in g.initializer if t.name in used and t.name not in new_inits]
    kept += [numpy_helper.from_array(v, k) for k, v in new_inits.items() if k in used]
    graph = helper.make_graph(nodes, g.name, list(g.input), list(g.output), kept)
    out_model = helper.make_model(graph, opset_imports=[o for o in model.opset_import if o.domain in ("", "ai.onnx")],
                                  producer_name="autopose requantise-detector")
    out_model.ir_version = model.ir_version
    onnx.checker.check_model(out_model)
    onnx.save(out_model, str(out_path))
    return {"weights": weights, "activations": clips}


def quantise_checked(float_path, out_path, int8_data, spec: DetectorSpec, calibration_images: int, log,
                     weight_bits: int = 8) -> dict:
    """:func:`quantise` calibrated on ``calibration_images`` of the ``synth`` split
    ``int8_data``; returns the manifest's ``int8`` entry (with how far int8 strays from the
    float graph on a few of those images)."""
    x_cal = calibration_inputs(int8_data, spec, calibration_images)
    log(f"int8: calibrating on {len(x_cal)} images of {int8_data}")
    quantise(float_path, out_path, x_cal, weight_bits)
    x_check = x_cal[:: max(1, len(x_cal) // 8)][:8]
    ref, got = run_graph(float_path, x_check), run_graph(out_path, x_check)
    C = len(spec.classes)
    q = {"calibration_data": str(int8_data), "calibration_images": int(len(x_cal)),
         "method": quant_method(weight_bits),
         "heatmap_max_abs_diff": float(np.abs(got[:, :C] - ref[:, :C]).max()),
         "box_channels_mean_abs_diff": float(np.abs(got[:, C:] - ref[:, C:]).mean())}
    log(f"int8 against float on {len(x_check)} calibration images: heatmaps max |diff| "
        f"{q['heatmap_max_abs_diff']:.3f}, box channels mean |diff| {q['box_channels_mean_abs_diff']:.4f}")
    return q


def _check_split(int8_data) -> None:
    if not Path(int8_data).is_dir():
        raise UserError(f"--int8 {int8_data}: not a folder; give a 'synth' split to calibrate the int8 detector on")


def _store_detector(src, out: Path, graph: Path, detector: dict) -> tuple[Manifest, float]:
    """Write ``out``: bundle ``src`` with ``graph`` as its detector and ``detector`` as the
    manifest's entry, staged and re-hashed (in place when ``out`` is ``src``'s folder); returns
    the verified manifest and the graph's size in MB."""
    with bundle_writer(src, out) as w:
        w.manifest.name = out.name
        w.manifest.detector = detector
        (w.folder / src.manifest.artefacts["detector"]).write_bytes(graph.read_bytes())
    return w.manifest, (out / src.manifest.artefacts["detector"]).stat().st_size / 1e6


def requantise_detector(model_dir, int8_data, out_dir=None, calibration_images: int = CALIBRATION_IMAGES,
                        weight_bits: int = 7, log=print, command: str | None = None) -> Manifest:
    """Write ``out_dir`` (default: ``model_dir`` in place): ``model_dir``'s bundle whose int8
    detector is quantised again (:func:`quantise`, ``weight_bits``) from its float32 graph
    (:func:`dequantise_graph`), calibrated on ``calibration_images`` of the ``synth`` split
    ``int8_data``; for a bundle whose float networks are gone. The manifest keeps the old
    ``int8`` entry under ``requantised_from``."""
    _check_bits(weight_bits)
    _check_split(int8_data)
    src = bundle_with_detector(model_dir)
    d0 = src.manifest.detector
    if "int8" not in d0:
        raise UserError(f"{model_dir}: its detector is not int8; quantise it with 'app.py lab join-detectors --int8 SPLIT'")
    spec = DetectorSpec.from_dict(d0)
    old = src.path("detector")
    out = Path(out_dir) if out_dir else src.root
    with tempfile.TemporaryDirectory() as tmp:
        flt, final = Path(tmp) / "float.onnx", Path(tmp) / "int8.onnx"
        n = dequantise_graph(old, flt)
        log(f"float32 graph of {old}: {n['weights']} quantised tensors restored, {n['activations']} activation "
            "quantisations made Clips")
        q = quantise_checked(flt, final, int8_data, spec, calibration_images, log, weight_bits)
        q.update(command=command or "app.py " + " ".join(sys.argv[1:]), created=time.strftime("%Y-%m-%d %H:%M:%S"),
                 requantised_from={"detector_sha256": sha256(old), **d0["int8"]})
        manifest, size = _store_detector(src, out, final, {**d0, "int8": q})
    log(f"bundle {out}: its detector quantised again (int8, {weight_bits}-bit weights), {size:.1f} MB")
    return manifest


def join_detectors(model_dir, others, out_dir=None, int8_data=None, calibration_images: int = CALIBRATION_IMAGES,
                   score_thresh: float | None = None, mirror: str = "none", weight_bits: int = 8,
                   half: bool = False, log=print, command: str | None = None) -> Manifest:
    """Write ``out_dir`` (default: ``model_dir`` in place): ``model_dir``'s bundle whose
    detector averages its own and ``others``' detectors (bundles; only their detectors are
    read), on the image or its mirror image as ``mirror`` says (``member_views``; with
    ``both`` one network can join itself; with ``int8_data`` or ``half`` and nothing else, one
    network is only quantised or halved). With ``int8_data`` (a ``synth`` split) the joined
    graph is quantised to int8, calibrated on ``calibration_images`` of its images, its
    weights in ``weight_bits`` (:func:`quantise`); with ``half`` its weights are stored in
    float16 (:func:`half_weights`). ``score_thresh``: the run-time threshold of the joined
    detector (default: the first member's); averaged heatmaps peak lower than each member's
    where the members' peaks do not coincide."""
    others = list(others or [])
    views = member_views(1 + len(others), mirror)
    if not others and mirror != "both" and int8_data is None and not half:
        raise UserError("nothing to join: name other bundles with --from, average the detector with its "
                        "mirror image (--mirror both), or store it alone as int8 (--int8 SPLIT) or with "
                        "float16 weights (--half-weights)")
    if not others and mirror == "alternate":
        raise UserError("--mirror alternate needs two networks or more (--from); one network sees its mirror "
                        "image with --mirror both")
    if half and int8_data is not None:
        raise UserError("--half-weights and --int8 exclude each other: int8 weights are smaller still")
    _check_bits(weight_bits)
    if weight_bits != 8 and int8_data is None:
        raise UserError(f"--weight-bits {weight_bits} is for int8 weights: give --int8 SPLIT too")
    if score_thresh is not None and not 0 < score_thresh < 1:
        raise UserError(f"--score-thresh must lie between 0 and 1, not {score_thresh}")
    if int8_data is not None:
        _check_split(int8_data)
    use = ("join the float networks it was made from (a bundle of 'build' keeps its float32 detector with "
           "--no-detector-int8)")
    src, spec0, d0, p0 = float_detector(model_dir, use)
    members = [(model_dir, spec0, d0, p0)] + [(o, *float_detector(o, use)[1:]) for o in others]
    for path, spec, _, _ in members[1:]:
        diff = [k for k in CONTRACT if getattr(spec, k) != getattr(spec0, k)]
        if diff:
            raise UserError(f"{path}: its detector differs from {model_dir}'s in {', '.join(diff)}; "
                            "only detectors of the same classes, input and kind of box can be averaged")
    out = Path(out_dir) if out_dir else src.root
    with tempfile.TemporaryDirectory() as tmp:
        joined = Path(tmp) / "joined.onnx"
        merge_graphs([p for *_, p in members], joined, mirror=mirror,
                     affine=[input_affine(spec, spec0) for _, spec, _, _ in members])
        info = {"members": len(members), "mirror": mirror, "views": [list(v) for v in views],
                "from": [{"bundle": str(path), "detector_sha256": sha256(p), "command": d.get("training", {}).get("command"),
                          "data": d.get("training", {}).get("data"), "steps": d.get("training", {}).get("steps"),
                          "normalisation": [spec.mean, spec.std]}
                         for path, spec, d, p in members],
                "note": "training is the first member's",
                "command": command or "app.py " + " ".join(sys.argv[1:]),
                "created": time.strftime("%Y-%m-%d %H:%M:%S")}
        final = joined
        if int8_data is not None:
            final = Path(tmp) / "int8.onnx"
            q = quantise_checked(joined, final, int8_data, spec0, calibration_images, log, weight_bits)
        if half:
            final = Path(tmp) / "half.onnx"
            x = np.random.default_rng(0).uniform(-2, 2, (2, 3, spec0.input_h, spec0.input_w)).astype(np.float32)
            hw = {"tensors": half_weights(joined, final), "storage": "float16, cast to float32 on loading",
                  "max_abs_diff_on_noise": float(np.abs(run_graph(final, x) - run_graph(joined, x)).max())}
            log(f"weights in float16: {hw['tensors']} tensors, outputs {hw['max_abs_diff_on_noise']:.2e} from float32's")
        detector = {**d0, "ensemble": info, **({"int8": q} if int8_data is not None else {}),
                    **({"half_weights": hw} if half else {})}
        if score_thresh is not None:
            detector["score_thresh"] = float(score_thresh)
        manifest, size = _store_detector(src, out, final, detector)
    seen = {"none": "", "both": " on the image and its mirror image", "alternate": ", the image and its mirror image by turns"}
    log(f"bundle {out}: a detector averaging {len(members)} network{'s' if len(members) > 1 else ''}{seen[mirror]}"
        + (" (int8)" if int8_data is not None else " (weights in float16)" if half else "") + f", {size:.1f} MB")
    return manifest
