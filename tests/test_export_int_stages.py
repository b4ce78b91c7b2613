"""The integer reader checks every stage against docs/reference/integer_format.md, never later.

Files are written here by an independent, unchecking writer (`_raw_file`, from the layout
table of the spec) so that the reader itself, not the writer, must refuse each invalid file.
A Hypothesis property mutates the released v1 file (hostile parameters, flipped payload
bits, CRCs recomputed so the mutation reaches the model checks): every mutant either fails
with IntegerFormatError or loads as a model whose NumPy runtime agrees with the plain-Python
oracle of the spec (tests/int_oracle.py), so nothing the reader accepts fails or overflows
later.
"""

import struct
import zlib
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from int_oracle import oracle_step

from torchseq.export.int_format import (
    PARAM_NAMES,
    PARAM_NAMES_V1,
    CohortStage,
    InputStage,
    IntegerFormatError,
    IntegerModel,
    L1Product,
    ReadoutStage,
    decode,
    encode,
    read_integer_model,
)
from torchseq.export.int_runtime import IntegerRuntime
from torchseq.export.int_stream import StreamRuntime

DATA = Path(__file__).resolve().parent / "data"
V1 = DATA / "int_format_v1.tsq"
# dtype codes and section order of the spec's tables (written out here, not imported)
CODES = {"u1": 1, "i1": 2, "u2": 3, "i2": 4, "i4": 5, "i8": 6}
ORDER = ["l1.cols", "l1.values", "l3.cols", "l3.values", "l3.row_scale", "cohort", "ring.cols",
         "ring.values", "unit_centre", "unit_to_ref"]


def _raw_file(params: dict, arrays: dict) -> bytes:
    """A .tsq file with valid CRCs and whatever contents: no model check at all."""
    def sec(name, a):
        a = np.ascontiguousarray(a)
        payload = a.astype(a.dtype.newbyteorder("<")).tobytes()
        dims = list(a.shape) + [0] * (4 - a.ndim)
        return struct.pack("<16sBBH4IQI", name.encode(), CODES[a.dtype.str[1:]],
                           a.ndim, 0, *dims, len(payload), zlib.crc32(payload)) + payload

    version, names = (2, PARAM_NAMES) if "readout" in params else (1, PARAM_NAMES_V1)
    body = sec("params", np.array([params[n] for n in names], "<i8"))
    body += b"".join(sec(n, arrays[n]) for n in ORDER)
    total = 32 + len(body) + 4
    head = struct.pack("<8sIIQ", b"TSQI\r\n\x1a\n", version, len(ORDER) + 1, total)
    head += struct.pack("<II", zlib.crc32(head), 0)
    data = head + body
    return data + struct.pack("<I", zlib.crc32(data))


@pytest.fixture(scope="module")
def v1():
    expected = np.load(DATA / "int_format_v1_expected.npz")
    return read_integer_model(V1).to_dict(), expected["frames"]


def _refused(params, arrays, match):
    """The dict path and the file path both refuse, with the same reason."""
    with pytest.raises(IntegerFormatError, match=match):
        IntegerModel.from_params(params, arrays)
    with pytest.raises(IntegerFormatError, match=match):
        decode(_raw_file(params, arrays), "mutant.tsq")


def test_raw_writer_agrees_with_the_library_writer(v1):
    d, _ = v1
    assert _raw_file(d["params"], d["arrays"]) == V1.read_bytes()


def test_hidden_of_32768_is_refused(v1):
    d, _ = v1
    p, a = dict(d["params"]), dict(d["arrays"])
    p.update(hidden=32768, l1_fan_in=1)
    a["l1.cols"] = np.zeros((32768, 1), "<u2")
    a["l1.values"] = np.ones((32768, 1), "<i2")
    _refused(p, a, "hidden 32768 not in 1..32767")


def test_n_input_of_32768_is_refused(v1):
    d, _ = v1
    p = dict(d["params"], height=128, width=256, n_input=32768)
    _refused(p, d["arrays"], "n_input 32768 not in 1..32767")
    p = dict(d["params"], height=128, width=256)  # n_input left at 768: inconsistent
    _refused(p, d["arrays"], "height\\*width = 128\\*256 is not below 32768")


def test_n_units_of_32768_is_refused(v1):
    d, _ = v1
    n = 32768
    p = dict(d["params"], n_units=n)
    a = {k: np.resize(v, (n,) + v.shape[1:]) if k not in ("l1.cols", "l1.values") else v
         for k, v in d["arrays"].items()}
    _refused(p, a, "n_units 32768 not in 1..32767")


@pytest.mark.parametrize("row, col, value, match", [
    (0, 0, -1, "unit_to_ref: spans must satisfy 0 <= first < last"),
    (3, 1, -7, "unit_to_ref: spans must satisfy 0 <= first < last"),
    (2, 1, None, "unit_to_ref: spans must satisfy 0 <= first < last"),  # last = first
])
def test_bad_unit_spans_are_refused(v1, row, col, value, match):
    d, _ = v1
    a = {k: np.array(v) for k, v in d["arrays"].items()}
    a["unit_to_ref"][row, col] = a["unit_to_ref"][row, 0] if value is None else value
    _refused(d["params"], a, match)


def test_centre_outside_its_span_is_refused(v1):
    d, _ = v1
    a = {k: np.array(v) for k, v in d["arrays"].items()}
    a["unit_centre"][4] = a["unit_to_ref"][4, 1]
    _refused(d["params"], a, "unit_centre: each centre must lie in its unit's span")


@pytest.mark.parametrize("name, value, match", [
    # the z-score numerator (n g - S) * norm_const: negative or foreign constants used to
    # reach round_div's 2**53 limit (ValueError) or wrap int64 in the runtime
    ("norm_const", -126910, "norm_const -126910 not in 0.."),
    ("norm_const", 126911, "norm_const 126911 is not round"),
    ("norm_const", 2**40, "norm_const .* is not round"),
    ({"sqrt_frac": 19, "norm_const": round(15**0.5 / 4 * 2**28)}, None,
     "sqrt_frac 19 takes the z-score's isqrt past 2\\*\\*62"),
    ("x_frac", 60, "norm_const .* is not round"),
    ("gain_const", 2**24, "gain_const 16777216 not in 1..16777215"),
    ("gain_const", 0, "gain_const 0 not in 1.."),
    ("gain_shift", 43, "gain_shift 43 takes the cohort divisor past 2\\*\\*62"),
    ("ring_frac", 62, "ring_frac 62 not in 0..61"),
    ("e_shift", 62, "e_shift 62 not in 0..61"),
    ("e_shift", 3, "e_shift 3 lets the rescaled evidence exceed 32767"),
    ("k", 0, "k 0 not in 1..256"),
    ("k", 257, "k 257 not in 1..256"),
    ("rectify", 2, "rectify 2 not in 0..1"),
    ("input_mode", 3, "input_mode 3 not in 0..1"),
    ("pool_h", 0, "pool_h 0 not in 1.."),
    ("pool_h", 1 << 12, "patch 4 with pool 4096x2 overflows the integer z-score"),
    ("patch", 5, "patch 5 does not tile 24x32"),
    ("window", -1, "window -1 not in 0..32767"),
    ("n_cohorts", 21, "n_cohorts 21 not in 1..20"),
    ("state_frac", 63, "state_frac 63 not in 0..62"),
])
def test_hostile_parameters_are_refused(v1, name, value, match):
    d, _ = v1
    edit = name if isinstance(name, dict) else {name: value}
    _refused(dict(d["params"], **edit), d["arrays"], match)


@pytest.mark.parametrize("section, index, value, match", [
    ("l3.values", (0, 0), -128, "l3.values: -128 is outside the symmetric int8 range"),
    ("l1.values", (1, 2), 2048, "l1.values: values exceed \\+-2047"),
    ("l1.values", (2, 0), -2048, "l1.values: values exceed \\+-2047"),
    ("l1.cols", (3, -1), 768, "l1.cols: index 768 out of range 0..767"),
    ("l3.cols", (4, -1), 65535, "l3.cols: index 65535 out of range"),
    ("l1.cols", (0, 1), None, "l1.cols: index lists must be strictly ascending"),
    ("l3.cols", (5, 1), None, "l3.cols: index lists must be strictly ascending"),
    ("l3.row_scale", (3,), -1, "l3.row_scale: scales must lie in 0..32768"),
    ("cohort", (0,), 1, "cohort: index 1 out of range 0..0"),
    ("ring.cols", (0, 0), 20, "ring.cols: index 20 out of range 0..19"),
])
def test_bad_section_values_are_refused(v1, section, index, value, match):
    d, _ = v1
    a = {k: np.array(v) for k, v in d["arrays"].items()}
    row = index[0]
    a[section][index] = a[section][row, 0] if value is None else value  # None: a repeat
    _refused(d["params"], a, match)


@pytest.mark.parametrize("value", [3.0, True, "12", None, np.float64(12.0)])
def test_parameters_must_be_integers(v1, value):
    d, _ = v1
    with pytest.raises(IntegerFormatError, match="gain_shift must be an integer"):
        IntegerModel.from_params(dict(d["params"], gain_shift=value), d["arrays"])


def test_stages_check_themselves(v1):
    d, _ = v1
    p, a = d["params"], d["arrays"]
    with pytest.raises(IntegerFormatError, match="n_input 40000 not in"):
        L1Product(a["l1.cols"], a["l1.values"], 40000)
    with pytest.raises(IntegerFormatError, match="patch 4 does not tile 6x32"):
        InputStage(6, 32, 2, 2, 4, 1, 9, 8, 126910)
    with pytest.raises(IntegerFormatError, match="gain_shift 33"):
        CohortStage(np.zeros(32767, "<u2"), 1, 100, 33, 16, 1)
    with pytest.raises(IntegerFormatError, match="section unit_centre: dtype int64"):
        ReadoutStage(a["unit_centre"].astype(np.int64), a["unit_to_ref"], 5)
    model = IntegerModel.from_params(p, a)
    with pytest.raises(ValueError, match="read-only"):
        model.l1.values[0, 0] = 1  # a checked model cannot be edited into an invalid one
    assert encode(model) == V1.read_bytes()


def test_a_model_holds_its_own_copy(v1):
    """Neither the decoded buffer nor the caller's arrays alias the model's (read-only) ones."""
    d, _ = v1
    data = bytearray(V1.read_bytes())
    model = decode(data)
    arrays = {k: np.array(v) for k, v in d["arrays"].items()}
    built = IntegerModel.from_params(d["params"], arrays)
    start, nbytes = _layout(bytes(data))[1][1:]  # l1.cols
    data[start:start + nbytes] = bytes(nbytes)
    arrays["l1.cols"][:] = 0
    for m in (model, built):
        assert not m.l1.cols.flags.writeable
        assert np.array_equal(m.l1.cols, d["arrays"]["l1.cols"])
    assert encode(model) == encode(built) == V1.read_bytes()


# --------------------------------------------------------------------- mutated v1 files
def _layout(data: bytes) -> list[tuple[int, int, int]]:
    """``(header offset, payload offset, payload bytes)`` of each section (from the spec)."""
    pos, out = 32, []
    for _ in range(struct.unpack_from("<I", data, 12)[0]):
        nbytes = struct.unpack_from("<Q", data, pos + 36)[0]
        out.append((pos, pos + 48, nbytes))
        pos += 48 + nbytes
    return out


def _reseal(data: bytearray) -> bytes:
    for head, start, nbytes in _layout(bytes(data)):
        data[head + 44:head + 48] = struct.pack("<I", zlib.crc32(bytes(data[start:start + nbytes])))
    data[-4:] = struct.pack("<I", zlib.crc32(bytes(data[:-4])))
    return bytes(data)


HOSTILE = [0, 1, -1, 2, 7, 62, 63, 64, 2**15 - 1, 2**15, 2**16, 2**24, 2**31 - 1, 2**31,
           2**53, 2**61, 2**62, 2**63 - 1, -2**63]
mutations = st.one_of(
    st.tuples(st.just("param"), st.integers(0, len(PARAM_NAMES_V1) - 1),
              st.one_of(st.sampled_from(HOSTILE), st.integers(-2**63, 2**63 - 1))),
    st.tuples(st.just("bit"), st.integers(1, len(ORDER)), st.integers(0, 2**31)),
)


@settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.too_slow],
          database=None)
@pytest.mark.slow  # an end-to-end run (CI's slow pass runs it)
@given(edits=st.lists(mutations, min_size=1, max_size=3))
def test_mutated_v1_files_are_refused_or_exact(v1, edits):
    _, frames = v1
    data = bytearray(V1.read_bytes())
    layout = _layout(bytes(data))
    for kind, which, value in edits:
        if kind == "param":
            data[80 + 8 * which:88 + 8 * which] = struct.pack("<q", value)
        else:
            _, start, nbytes = layout[which]
            data[start + (value >> 3) % nbytes] ^= 1 << (value & 7)
    try:
        model = decode(_reseal(data), "mutant.tsq")
    except IntegerFormatError as err:
        assert str(err).startswith("mutant.tsq: ")
        return
    _runs_as_the_spec_says(model, frames)


def _runs_as_the_spec_says(model, frames, steps=2):
    """Runtime == oracle step by step from a zero state; the time-batched runtime agrees."""
    runtime = IntegerRuntime(model)
    ph, pw = model.input.pool_h, model.input.pool_w
    h, w = model.input.height * ph, model.input.width * pw
    src = np.resize(frames[:steps], (steps, h, w)).astype(np.uint8)
    state = runtime.initial_state(1)
    oracle_state = [0] * runtime.n_units
    for t in range(steps):
        out, state = runtime.step(src[t:t + 1], state)
        act, ref, conf = oracle_step(model, src[t].tolist(), oracle_state)
        oracle_state = act
        assert state[0].tolist() == act
        assert (int(out.reference[0]), int(out.confidence[0])) == (ref, conf)
    ref, conf, act = StreamRuntime(model, chunk=1).run(src)
    assert np.array_equal(act[-1], state[0]) and ref[-1] == out.reference[0]
    assert conf[-1] == out.confidence[0]


@pytest.mark.parametrize("edit", [
    {"ring_frac": 0, "rectify": 0},  # no rounding shift: m itself, of both signs
    {"ring_frac": 61},
    {"gain_shift": 42},  # 20 units * 32767 * 2**42 < 2**62: the largest accepted
    {"gain_const": 2**24 - 1},
    {"e_shift": 61},
    {"window": 32767},
    {"rectify": 0, "n_cohorts": 4, "k": 256},
])
def test_accepted_extremes_run_as_the_spec_says(v1, edit):
    d, frames = v1
    a = {k: np.array(v) for k, v in d["arrays"].items()}
    if "n_cohorts" in edit:
        a["cohort"] = (np.arange(20) * 4 // 20).astype("<u2")
    if edit.get("ring_frac") == 0:  # a ring of weight 1 on 2**0: no saturation in 3 steps
        a["ring.values"][:, 0], a["ring.values"][:, 1:] = 1, 0
    _runs_as_the_spec_says(IntegerModel.from_params(dict(d["params"], **edit), a), frames, 3)
