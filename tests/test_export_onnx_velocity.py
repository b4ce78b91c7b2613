"""Float ONNX of the adaptive-velocity model (``ring_velocity="adaptive"``).

References: the eager model stepped frame by frame (``NeuralSeqSLAM.step``, the same
``adaptive_step`` the graph is traced from, run with the model's own kernels), and the demo
route's true speed (0.8x and 1.3x) for the speed estimate the graph carries.
"""

import json

import numpy as np
import onnx
import pytest
import torch

from torchseq.cli.export import main, summary_lines
from torchseq.demo import make_demo
from torchseq.export import ExportError, export_checkpoint
from torchseq.export.contract import read_contract
from torchseq.export.onnx_float import (
    StreamingStep,
    build_float_onnx,
)
from torchseq.export.sessions import run_float_onnx, run_velocity_onnx, session
from torchseq.neural import NeuralConfig, NeuralSeqSLAM
from torchseq.preprocess import resize

N_REF = 100
SPEEDS = (0.8, 1.3)


@pytest.fixture(scope="module")
def setup():
    routes = {s: make_demo(n_reference=N_REF, size=(48, 64), speed=s, seed=4) for s in SPEEDS}
    model = NeuralSeqSLAM(NeuralConfig.adaptive_velocity(hidden=512, n_output=N_REF))
    model.fit(routes[SPEEDS[0]].reference, log=False)  # the same reference at both speeds
    small = {s: resize(r.query.float(), model.config.input_size) for s, r in routes.items()}
    return model, routes, small, build_float_onnx(model)


def eager_steps(model, frames):
    """The eager model frame by frame, ``frames`` ``(T, B, h, w)``: its outputs and speeds."""
    state, refs, confs, acts, vels = None, [], [], [], []
    for f in frames:
        out, state = model.step(f, state)
        refs.append(out.reference)
        confs.append(out.confidence)
        acts.append(out.activity)
        vels.append(state.velocity)
    return [torch.stack(x).numpy() for x in (refs, confs, acts, vels)]


def test_graph_takes_and_returns_the_velocity_state(setup):
    model, *_, proto = setup
    k = model.config.velocity_window
    ins = {i.name: i.type.tensor_type for i in proto.graph.input}
    outs = [o.name for o in proto.graph.output]
    assert list(ins) == ["frames", "state", "velocity", "positions", "count"]
    assert outs == ["activity", "new_state", "reference", "confidence", "new_velocity",
                    "new_positions", "new_count"]
    assert ins["velocity"].elem_type == onnx.TensorProto.DOUBLE
    assert ins["count"].elem_type == onnx.TensorProto.INT64
    assert ins["positions"].shape.dim[1].dim_value == k
    assert ins["state"].shape.dim[0].dim_param == "batch"


@pytest.mark.parametrize("speed", SPEEDS)
def test_onnx_steps_like_the_eager_model(setup, speed):
    """Frame by frame, state fed back: same decision on every frame, same speed estimate."""
    model, routes, small, proto = setup
    ref, conf, act, vel = run_velocity_onnx(session(proto), small[speed].numpy())
    want_ref, want_conf, want_act, want_vel = eager_steps(model, small[speed][:, None])
    assert np.array_equal(ref, want_ref[:, 0])  # every frame (measured: all equal)
    np.testing.assert_allclose(vel, want_vel[:, 0], atol=1e-5, rtol=0)
    np.testing.assert_allclose(act, want_act[:, 0], atol=1e-4, rtol=1e-4)
    np.testing.assert_allclose(conf, want_conf[:, 0], atol=1e-4, rtol=1e-4)
    # the graph's speed is the route's (an independent figure), not a constant 1
    assert abs(vel[-1] - speed) < 0.05
    assert vel.min() < 0.9 if speed < 1 else vel.max() > 1.2
    # run_float_onnx reads the graph's inputs and feeds the whole state back too
    assert np.array_equal(run_float_onnx(session(proto), small[speed].numpy())[0], ref)
    # and the model's own run (its fastest kernels) reports the same places
    run = model.run(routes[speed].query).matches.reference.numpy()
    assert np.mean(run == ref) >= 0.99


def test_dynamic_batch_two_streams_at_two_speeds(setup):
    """One graph call steps a 0.8x and a 1.3x stream together, each at its own speed."""
    model, _, small, proto = setup
    t_len = min(len(s) for s in small.values())
    frames = torch.stack([small[s][:t_len] for s in SPEEDS], dim=1)  # (T, 2, h, w)
    sess = session(proto)
    state = [x.numpy() for x in StreamingStep(model).initial_state(2)]
    names = ["state", "velocity", "positions", "count"]
    refs, vels = [], []
    for f in frames.numpy():
        act, new_state, ref, conf, *rest = sess.run(None, {"frames": f,
                                                           **dict(zip(names, state))})
        state = [new_state, *rest]
        refs.append(ref)
        vels.append(rest[0])
    want_ref, _, want_act, want_vel = eager_steps(model, frames)
    assert np.array_equal(np.stack(refs), want_ref)
    np.testing.assert_allclose(np.stack(vels), want_vel, atol=1e-5, rtol=0)
    np.testing.assert_allclose(act, want_act[-1], atol=1e-4, rtol=1e-4)
    assert abs(vels[-1][0] - 0.8) < 0.05 and abs(vels[-1][1] - 1.3) < 0.05


def test_streaming_step_checks_its_state_arguments(setup):
    model, _, small, _ = setup
    step = StreamingStep(model)
    with pytest.raises(ExportError, match="velocity, positions and count"):
        step(small[0.8][:1], torch.zeros(1, model.n_units))
    fixed = NeuralSeqSLAM(NeuralConfig(hidden=512, n_output=N_REF))
    fixed.fit(make_demo(n_reference=N_REF, size=(48, 64), seed=4).reference, log=False)
    with pytest.raises(ExportError, match="no velocity state"):
        StreamingStep(fixed)(small[0.8][:1], *step.initial_state(1))
    assert StreamingStep(fixed).input_names == ("frames", "state")


# ---------------------------------------------------------------- the export command
SKIPPED = "no spiking form of ring_velocity='adaptive'"


@pytest.mark.slow  # an end-to-end run (CI's slow pass runs it)
def test_export_command_writes_every_form_but_nir(setup, tmp_path, capsys):
    model, routes, *_ = setup
    route = routes[1.3]
    model.save(tmp_path / "m.pt")
    np.save(tmp_path / "q.npy", route.query.numpy())
    np.save(tmp_path / "gt.npy", route.ground_truth)
    out = tmp_path / "out"
    code = main([str(tmp_path / "m.pt"), "--out", str(out), "--query", str(tmp_path / "q.npy"),
                 "--ground-truth", str(tmp_path / "gt.npy")])
    printed = capsys.readouterr().out.splitlines()
    assert code == 0 and printed[-1] == "PASS"
    assert not any(line.startswith("integer: skipped") for line in printed)
    assert f"nir: skipped ({SKIPPED})" in printed
    report = json.loads((out / "validation.json").read_text())
    assert "integer" not in report and report["nir"] == {"skipped": SKIPPED}
    assert report["passed"] and report["float_onnx_agreement"] >= 0.99
    assert report["integer_format_version"] == 3 and report["integer_onnx_bit_exact"]
    assert report["integer_agreement"] >= 0.99 and report["integer_speed_max_abs_error"] < 1e-3
    assert report["recall_at_1"]["float_onnx"] == report["recall_at_1"]["pytorch"] >= 0.9
    assert sorted(p.name for p in out.iterdir()) == [
        "model_float.onnx", "model_int.onnx", "model_int.tsq", "model_quant.onnx",
        "validation.json"]
    props = read_contract(out / "model_float.onnx")
    assert "velocity ones float64 (B,)" in props["torchseq.initial_state"]
    assert f"(B, {model.config.velocity_window})" in props["torchseq.initial_state"]
    props = read_contract(out / "model_int.onnx")
    assert "velocity 65536 int64 (B,)" in props["torchseq.initial_state"]
    # the graph written is the one validated: it steps the 1.3x route at its speed
    small = resize(route.query.float(), model.config.input_size).numpy()
    vel = run_velocity_onnx(session(out / "model_float.onnx"), small)[3]
    assert abs(vel[-1] - 1.3) < 0.05


@pytest.mark.slow  # an end-to-end run (CI's slow pass runs it)
def test_export_fails_when_the_graph_disagrees(setup, tmp_path, monkeypatch):
    """A graph that decides otherwise than the model is a FAIL, not a skip."""
    import torchseq.export.validate as validate

    model, routes, *_ = setup
    model.save(tmp_path / "m.pt")
    real = validate.run_float_onnx

    def shifted(sess, frames):
        ref, conf, act = real(sess, frames)
        return ref + 1, conf, act

    monkeypatch.setattr(validate, "run_float_onnx", shifted)
    assert not export_checkpoint(tmp_path / "m.pt", tmp_path / "out", routes[0.8].query,
                                 nir=False)
    assert summary_lines(tmp_path / "out")[-1] == "FAIL: float_onnx_agreement"


@pytest.mark.slow  # an end-to-end run (CI's slow pass runs it)
def test_export_on_the_checkpoints_own_reference(tmp_path):
    """``train --export``'s path: no query, the demo route recorded in the checkpoint."""
    demo = make_demo(n_reference=60, seed=1)
    model = NeuralSeqSLAM(NeuralConfig.adaptive_velocity(hidden=512, n_output=60))
    model.fit(demo.reference, log=False)
    model.save(tmp_path / "m.pt", extra={"reference": {"source": "demo", "demo_frames": 60,
                                                       "demo_seed": 1}})
    assert export_checkpoint(tmp_path / "m.pt", tmp_path / "out")
    lines = summary_lines(tmp_path / "out")
    assert lines[0].startswith("validated on the checkpoint's own reference: demo route")
    assert f"nir: skipped ({SKIPPED})" in lines and lines[-1] == "PASS"
    assert any(line.startswith("device input") for line in lines)  # the integer device
    report = json.loads((tmp_path / "out" / "validation.json").read_text())
    assert report["recall_at_1"]["float_onnx"] == report["recall_at_1"]["pytorch"]
