"""The adaptive ring in the integer format (version 3): docs/reference/integer_format.md,
steps 7v and 9.

References: an independent plain-Python oracle of the velocity ring and the speed estimator
below (Python integers and exact fractions: the LS slope and the residual test as rationals,
sharing no code with torchseq), the float model stepped frame by frame (decisions and its
float64 speed estimate), and the released version-1 file plus a pinned version-2 digest for
the byte identity of fixed models.
"""

import hashlib
import math
import struct
import zlib
from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest
import torch
from int_oracle import oracle_step, round_half_away

import torchseq.export.int_format as int_format
from torchseq.demo import make_demo
from torchseq.export.int_format import (
    IntegerFormatError,
    IntegerModel,
    decode,
    encode,
    read_integer_model,
)
from torchseq.export.int_functional import velocity_ring, velocity_update
from torchseq.export.int_model import device_frames, integer_model
from torchseq.export.int_onnx import build_integer_onnx
from torchseq.export.int_runtime import IntegerRuntime
from torchseq.export.int_stream import StreamRuntime
from torchseq.export.int_velocity import (
    IntVelocityState,
    VelocityStepModule,
    initial_velocity_state,
)
from torchseq.export.sessions import run_integer_onnx, session
from torchseq.neural import NeuralConfig, NeuralSeqSLAM

DATA = Path(__file__).parent / "data"
ONE = 2**16
N_REF = 100
# sha256 of encode() of the released version-1 model with readout = 1, written by the
# version-2 writer before version 3 existed (main at d48461d): fixed models keep their bytes
V2_SHA256 = "ed53ccdd125ab3b9b2d5fd8d366e94068e407fbc4260afcc9413e2849a8f732c"


@pytest.fixture(scope="module")
def setup():
    routes = {s: make_demo(n_reference=N_REF, size=(48, 64), speed=s, seed=4) for s in (0.8, 1.3)}
    model = NeuralSeqSLAM(NeuralConfig.adaptive_velocity(hidden=512, n_output=N_REF))
    model.fit(routes[0.8].reference, log=False)
    im = integer_model(model)
    frames = {s: device_frames(r.query, model.config.input_size, (1, 1))
              for s, r in routes.items()}
    return model, im, frames


# ---------------------------------------------------------------- the oracle
def oracle_ring(im, state, g, speed):
    """Step 7v: powers of the stored shift, the two-power mix, decay, evidence (exact)."""
    p, a, st = im.params, im.arrays, im.velocity
    one, n_units = 2 ** p["ring_frac"], p["n_units"]
    powers = [list(state)]
    cols, shift = a["ring.cols"].tolist(), a["ring.shift"].tolist()  # Python ints (faster sums)
    for _ in range(-(-st.v_max // ONE)):
        prev = powers[-1]
        nxt = []
        for u in range(n_units):
            m = sum(v * prev[c] for c, v in zip(cols[u], shift[u]))
            nxt.append(max(-(2**31 - 1), min(2**31 - 1, round_half_away(Fraction(m, one)))))
        powers.append(nxt)
    n, f = divmod(speed, ONE)
    hi = powers[n + 1] if f else [0] * n_units
    act = []
    for u in range(n_units):
        moved = round_half_away(Fraction((ONE - f) * powers[n][u] + f * hi[u], ONE))
        val = round_half_away(Fraction(st.decay_const * moved, one)) + g[u]
        act.append(max(-(2**31 - 1), min(2**31 - 1, val)))
    return act


def oracle_fit(pos):
    """The LS slope of ``pos`` against ``0..K-1`` and its largest residual (exact)."""
    k = len(pos)
    tbar = Fraction(k - 1, 2)
    mean = Fraction(sum(pos), k)
    slope = (sum((i - tbar) * (pos[i] - mean) for i in range(k))
             / sum((i - tbar) ** 2 for i in range(k)))
    return slope, max(abs(pos[i] - mean - slope * (i - tbar)) for i in range(k))


def oracle_update(im, speed, positions, count, reference):
    """Step 9 as the float estimator writes it, in exact rationals, then the Q16 grid."""
    st = im.velocity
    k = st.window
    pos = list(positions[1:]) + [reference]
    count = min(count + 1, k)
    slope, worst = oracle_fit(pos)
    trusted = count >= k and worst <= Fraction(st.tolerance, ONE)
    target = max(-2**36, min(2**36, round_half_away(slope * ONE))) if trusted else ONE
    v = speed + round_half_away(Fraction(st.rate * (target - speed), ONE)) if count >= k else ONE
    return max(st.v_min, min(st.v_max, v)), pos, count


def oracle_run(im, frames):
    """Whole stream: the oracle's drive (oracle_step from a zero state), ring, centre read-out
    and estimator."""
    n_units, k = im.params["n_units"], im.velocity.window
    state, speed, pos, count = [0] * n_units, ONE, [0] * k, 0
    out = []
    for frame in frames:
        g = oracle_step(im, frame.tolist(), [0] * n_units)[0]  # zero state: act = g
        state = oracle_ring(im, state, g, speed)
        best = max(range(n_units), key=lambda u: (state[u], -u))
        ref = int(im.arrays["unit_centre"][best])
        speed, pos, count = oracle_update(im, speed, pos, count, ref)
        out.append((ref, speed, list(state)))
    return out


# ---------------------------------------------------------------- runtimes vs the oracle
def test_estimator_kernels_follow_the_oracle_exactly(setup):
    """Random windows (straight lines with noise, jumps, scatter) and speeds."""
    _, im, _ = setup
    rt = IntegerRuntime(im)
    mod = VelocityStepModule(im)
    st = im.velocity
    rng = np.random.default_rng(0)
    k, batch = st.window, 64
    trusted = []
    for trial in range(12):
        slope = rng.uniform(-2, 5.5, batch)  # lines that stay inside the 100 frames
        lo, hi = np.maximum(0, -slope * k), N_REF - 1 - np.maximum(0, slope * k)
        start = rng.uniform(lo, hi)
        line = np.round(start[:, None] + slope[:, None] * np.arange(k + 1)).astype(np.int64)
        noise = trial % 5  # up to 4 frames: around the tolerance (3 frames)
        line += rng.integers(-noise, noise + 1, (batch, k + 1))
        line[::7, rng.integers(0, k + 1)] += rng.integers(-50, 50)  # relocalisation jumps
        line = np.clip(line, 0, N_REF - 1)
        pos, ref = line[:, :k], line[:, k]  # the window and the next decision on its line
        ref[::5] = rng.integers(0, N_REF, ref[::5].shape)  # scattered decisions
        speed = rng.integers(st.v_min, st.v_max + 1, batch)
        count = rng.integers(k - 2, k + 1, batch)
        act = np.zeros((batch, im.params["n_units"]), np.int32)
        got = rt.velocity_update(IntVelocityState(act, speed, pos, count), ref, act)
        v_t, p_t, c_t = velocity_update(torch.tensor(speed), torch.tensor(pos),
                                        torch.tensor(count), torch.tensor(ref), mod.velocity)
        for b in range(batch):
            want = oracle_update(im, int(speed[b]), pos[b].tolist(), int(count[b]), int(ref[b]))
            assert (int(got.velocity[b]), got.positions[b].tolist(), int(got.count[b])) == want
            assert (int(v_t[b]), p_t[b].tolist(), int(c_t[b])) == want
            worst = oracle_fit(want[1])[1]
            if want[2] == k:
                trusted.append(worst <= Fraction(st.tolerance, ONE))
    # both branches of the residual test, each many times
    assert 100 < sum(trusted) < len(trusted) - 100


def test_ring_kernels_follow_the_oracle_exactly(setup):
    """Random int32 states, evidence and every speed class (n = 0..top, f = 0 and not)."""
    _, im, _ = setup
    rt = IntegerRuntime(im)
    mod = VelocityStepModule(im)
    rng = np.random.default_rng(1)
    n_units = im.params["n_units"]
    speeds = np.array([im.velocity.v_min, ONE, ONE + 1, 3 * ONE // 2, 2 * ONE - 1, 2 * ONE,
                       im.velocity.v_max, 54321, 70000, 100000])
    state = rng.integers(-2**31 + 1, 2**31, (speeds.size, n_units)).astype(np.int32)
    state[:3] //= 2**12
    g = rng.integers(-2**20, 2**20, (speeds.size, n_units))
    got = rt.velocity_ring(state, g, speeds)
    got_t = velocity_ring(torch.tensor(state), torch.tensor(g), torch.tensor(speeds),
                          mod.ring_cols, mod.ring_shift, im.params["ring_frac"], im.velocity)
    for b in range(speeds.size):
        want = oracle_ring(im, state[b].tolist(), g[b].tolist(), int(speeds[b]))
        assert got[b].tolist() == want and got_t[b].tolist() == want


def test_every_integer_form_follows_the_oracle_on_a_stream(setup):
    model, im, frames = setup
    fr = frames[1.3][:40]
    want = oracle_run(im, fr)
    ref, conf, act, speed = IntegerRuntime(im).run(fr, speeds=True)
    outs = {"numpy": (ref, conf, act, speed),
            "module": IntegerRuntime(im, kernel="torch").run(fr, speeds=True),
            "stream": StreamRuntime(im).run_speeds(fr),
            "onnx": run_integer_onnx(session(build_integer_onnx(im)), fr, speeds=True)}
    for name, (r, c, a, v) in outs.items():
        assert r.tolist() == [w[0] for w in want], name
        assert v.tolist() == [w[1] for w in want], name
        assert a.tolist() == [w[2] for w in want], name
        assert np.array_equal(c, conf) and a.dtype == np.int32, name
    assert len(set(speed.tolist())) > 3  # the speed moved: not a test of a constant


def test_module_kernel_runs_the_velocity_step(setup):
    """STYLE habit 9: the module kernel is the version-3 definition, the NumPy one its own."""
    _, im, frames = setup
    assert isinstance(IntegerRuntime(im, kernel="torch").module, VelocityStepModule)
    rt = IntegerRuntime(im)
    assert rt.module is None and rt.velocity is im.velocity
    out, state = rt.step(frames[0.8][:2])
    assert isinstance(state, IntVelocityState) and out.speed.shape == (2,)


# ---------------------------------------------------------------- agreement with float
@pytest.mark.parametrize("speed", [0.8, 1.3])
def test_integer_agrees_with_the_float_model(setup, speed):
    model, im, frames = setup
    fr = frames[speed]
    ref, _, _, v = StreamRuntime(im).run_speeds(fr)
    state, refs, vels = None, [], []
    with torch.no_grad():
        for t in range(fr.shape[0]):
            out, state = model.step(torch.from_numpy(fr[t:t + 1]).float(), state)
            refs.append(int(out.reference[0]))
            vels.append(float(state.velocity[0]))
    assert np.mean(ref == np.array(refs)) >= 0.99
    assert np.abs(v / ONE - np.array(vels)).max() < 1e-3
    assert abs(v[-1] / ONE - speed) < 0.05  # it tracks the route's true speed


# ---------------------------------------------------------------- the file
def test_fixed_models_keep_their_bytes():
    data = (DATA / "int_format_v1.tsq").read_bytes()
    v1 = decode(data)
    assert v1.format_version == 1 and encode(v1) == data
    d = v1.to_dict()
    d["format_version"], d["params"]["readout"] = 2, 1
    v2 = IntegerModel.from_dict(d)
    assert v2.format_version == 2 and v2.velocity is None
    assert hashlib.sha256(encode(v2)).hexdigest() == V2_SHA256
    assert decode(encode(v2)).format_version == 2


def test_adaptive_model_is_version_3_and_round_trips(setup, tmp_path):
    _, im, frames = setup
    data = encode(im)
    assert struct.unpack_from("<I", data, 8)[0] == 3 and im.format_version == 3
    int_format.write_integer_model(tmp_path / "m.tsq", im)
    back = read_integer_model(tmp_path / "m.tsq")
    assert encode(back) == data and back.params == im.params
    assert np.array_equal(back.velocity.shift, im.velocity.shift)
    d = im.to_dict()
    assert d["format_version"] == 3 and "ring.shift" in d["arrays"]
    assert encode(IntegerModel.from_dict(d)) == data


def _with_version(data: bytes, version: int) -> bytes:
    head = bytearray(data[:32])
    struct.pack_into("<I", head, 8, version)
    struct.pack_into("<I", head, 24, zlib.crc32(bytes(head[:24])))
    body = bytes(head) + data[32:-4]
    return body + struct.pack("<I", zlib.crc32(body))


def test_a_reader_of_version_2_refuses_version_3(setup, monkeypatch):
    _, im, _ = setup
    data = encode(im)
    monkeypatch.setattr(int_format, "SUPPORTED_VERSIONS", (1, 2))  # the version-2 reader
    with pytest.raises(IntegerFormatError, match="unsupported format_version 3"):
        decode(data)
    monkeypatch.undo()
    # the same bytes labelled version 2: 31 parameters and a ring.shift section are refused
    with pytest.raises(IntegerFormatError, match="version 2 holds 25 parameters"):
        decode(_with_version(data, 2))


@pytest.mark.parametrize("name, value, match", [
    ("v_max", 8 * ONE + 1, "v_max"), ("v_min", ONE + 1, "v_min"), ("v_rate", 0, "v_rate"),
    ("velocity_window", 2, "velocity_window"), ("decay_const", -1, "decay_const"),
    ("velocity_window", 4096, "overflow the speed fit"),
])
def test_reader_checks_the_velocity_parameters(setup, name, value, match):
    _, im, _ = setup
    d = im.to_dict()
    d["params"][name] = value
    with pytest.raises(IntegerFormatError, match=match):
        IntegerModel.from_dict(d)


def test_runtime_checks_the_velocity_state(setup):
    _, im, frames = setup
    rt = IntegerRuntime(im)
    good = initial_velocity_state(1, im.params["n_units"], im.velocity.window)
    with pytest.raises(ValueError, match="IntVelocityState"):
        rt.step(frames[0.8][:1], good.activity)
    with pytest.raises(ValueError, match="v_min, v_max"):
        rt.step(frames[0.8][:1], good._replace(velocity=np.array([9 * ONE])))
    with pytest.raises(ValueError, match="fixed ring"):
        IntegerRuntime(decode((DATA / "int_format_v1.tsq").read_bytes())).run(
            np.zeros((1, 1, 1), np.uint8), speeds=True)
    assert math.isclose(good.velocity[0] / ONE, 1.0)


def test_largest_window_the_reader_accepts_stays_exact(setup):
    """At the bounds the reader checks (largest K for these 100 frames, largest tolerance),
    extreme windows (0 and F - 1 alternating, lines of slope up to F) follow the oracle:
    the int64 arithmetic does not overflow anywhere the reader lets it run."""
    _, im, _ = setup
    d = im.to_dict()
    k = 3
    while True:  # the largest K the reader accepts for F = 100
        d["params"]["velocity_window"] = k + 1
        try:
            IntegerModel.from_dict(d)
        except IntegerFormatError:
            break
        k += 1
    d["params"]["velocity_window"] = k
    assert 64 < k < 4096
    den = k * (k * k - 1) // 6
    d["params"]["v_tolerance"] = (2**62 - 1) // (2 * k * den)
    wide = IntegerModel.from_dict(d)
    d["params"]["v_tolerance"] += 1
    with pytest.raises(IntegerFormatError, match="overflow"):
        IntegerModel.from_dict(d)
    rt, mod = IntegerRuntime(wide), VelocityStepModule(wide)
    rng = np.random.default_rng(2)
    pos = np.stack([np.arange(k) % 2 * (N_REF - 1), np.full(k, N_REF - 1),
                    np.minimum(np.arange(k), N_REF - 1), rng.integers(0, N_REF, k)])
    speed = np.array([wide.velocity.v_max, wide.velocity.v_min, ONE, ONE])
    count, ref = np.full(4, k), np.array([N_REF - 1, 0, N_REF - 1, 50])
    act = np.zeros((4, wide.params["n_units"]), np.int32)
    got = rt.velocity_update(IntVelocityState(act, speed, pos, count), ref, act)
    v_t = velocity_update(torch.tensor(speed), torch.tensor(pos), torch.tensor(count),
                          torch.tensor(ref), mod.velocity)[0]
    for b in range(4):
        want = oracle_update(wide, int(speed[b]), pos[b].tolist(), k, int(ref[b]))
        assert int(got.velocity[b]) == int(v_t[b]) == want[0]


@pytest.mark.parametrize("value", [2**20 + 1, -(2**20) - 1])
def test_reader_bounds_the_velocity_shift(setup, value):
    """``ring.shift`` is read with ``abs <= 2**20``: the velocity ring's int64 sums
    (``check_fits``: width * 2**20 * INT32_MAX < A_BOUND) rely on it."""
    _, im, _ = setup
    d = im.to_dict()
    shift = np.array(d["arrays"]["ring.shift"], np.int32, copy=True)
    assert int(np.abs(shift.astype(np.int64)).max()) <= 2**20  # the model's own shift passes
    shift.flat[0] = value
    d["arrays"]["ring.shift"] = shift
    with pytest.raises(IntegerFormatError, match=r"ring\.shift: values must satisfy abs"):
        IntegerModel.from_dict(d)
    shift.flat[0] = 2**20 if value > 0 else -(2**20)  # the bound itself is accepted
    assert IntegerModel.from_dict(d).velocity.shift.flat[0] == shift.flat[0]
