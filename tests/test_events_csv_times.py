"""CSV event times written as floats follow the one float-time rule (torchseq.events.times).

Expected values come from the rule's own statement (fractions under 1e5 are seconds,
rounded to us; whole numbers are us; fractions beyond 1e5 are refused) computed here with
Python's decimal arithmetic, and from the same times stored in an ``.npz`` (another reader
under the same rule).
"""

import warnings
from decimal import Decimal

import numpy as np
import pytest

from torchseq.events import EventFormatError, read_events


def _csv(tmp_path, text, name="e.csv"):
    (tmp_path / name).write_text(text)
    return tmp_path / name


def test_fractional_times_are_seconds_with_a_warning(tmp_path):
    times = ["0.5", "1.0000004", "1.25", "2.0000006", "99999.999999"]
    path = _csv(tmp_path, "t,x,y,p\n" + "".join(f"{t},1,2,1\n" for t in times))
    with pytest.warns(UserWarning, match="read as seconds"):
        s = read_events(path, sensor_size=(4, 4))
    want = [int((Decimal(t) * 10**6).to_integral_value()) for t in times]
    assert s.events["t"].tolist() == want


def test_same_times_as_an_npz_with_float_seconds(tmp_path):
    rng = np.random.default_rng(0)
    t = np.sort(rng.random(50) * 30)
    x, y, p = rng.integers(0, 8, 50), rng.integers(0, 6, 50), rng.integers(0, 2, 50)
    path = _csv(tmp_path, "x y polarity timestamp\n" + "".join(
        f"{a} {b} {c} {d!r}\n" for a, b, c, d in zip(x, y, p, t.tolist())))
    np.savez(tmp_path / "e.npz", t=t, x=x, y=y, p=p)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        a = read_events(path, sensor_size=(8, 6))
        b = read_events(tmp_path / "e.npz", sensor_size=(8, 6))
    assert np.array_equal(a.events, b.events) and a.events["t"].max() > 10**6


def test_whole_numbers_are_exact_microseconds(tmp_path):
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # plain integers: no warning
        s = read_events(_csv(tmp_path, "10,1,1,1\n20,1,1,0\n"), sensor_size=(4, 4))
    assert s.events["t"].tolist() == [10, 20]
    with pytest.warns(UserWarning, match="whole seconds"):
        s = read_events(_csv(tmp_path, "10.0,1,1,1\n2e1,1,1,0\n"), sensor_size=(4, 4))
    assert s.events["t"].tolist() == [10, 20]
    big = _csv(tmp_path, "9007199254740993.0,1,2,1\n9007199254740995,1,2,1\n")
    assert read_events(big, sensor_size=(4, 4)).events["t"].tolist() == [
        9007199254740993, 9007199254740995]  # exact: not through float64


@pytest.mark.parametrize("t, match", [("123456.5", "too large to be seconds"),
                                      ("nan", "NaN or infinite"),
                                      ("0.5s", "line 3: time '0.5s' is not a number")])
def test_unclear_or_bad_float_times_are_refused(tmp_path, t, match):
    path = _csv(tmp_path, f"t,x,y,p\n0.25,1,1,1\n{t},1,1,1\n")
    with pytest.raises(EventFormatError, match=match) as err:
        read_events(path, sensor_size=(4, 4))
    assert str(err.value).startswith(str(path)) and str(err.value).count(str(path)) == 1


def test_integer_columns_stay_exact_beside_float_times(tmp_path):
    path = _csv(tmp_path, "t,x,y,p\n0.5,3.0,2,-1\n0.75,5,1e0,1\n")
    with pytest.warns(UserWarning):
        s = read_events(path, sensor_size=(8, 8))
    assert s.events["x"].tolist() == [3, 5] and s.events["y"].tolist() == [2, 1]
    assert s.events["p"].tolist() == [0, 1] and s.events["t"].tolist() == [500000, 750000]
    bad = "'2.5' is not an integer"
    with pytest.raises(EventFormatError, match=bad), pytest.warns(UserWarning):
        read_events(_csv(tmp_path, "0.5,2.5,1,1\n", "f.csv"), sensor_size=(8, 8))


def test_a_declared_unit_scales_without_guessing(tmp_path):
    # epoch seconds with fractions: refused by the rule, read exactly once the unit is declared
    times = ["1700000000.25", "1700000000.500001"]
    path = _csv(tmp_path, "t,x,y,p\n" + "".join(f"{t},1,2,1\n" for t in times))
    with pytest.raises(EventFormatError, match="too large to be seconds"):
        read_events(path, sensor_size=(4, 4))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # declared: no guess, no warning
        s = read_events(path, sensor_size=(4, 4), time_unit="s")
    want = [int((Decimal(t) * 10**6).to_integral_value()) for t in times]
    assert s.events["t"].tolist() == want
    # integer columns in a declared unit stay exact: ms scaled, ns floored like HDF5 columns
    ints = _csv(tmp_path, "7,1,1,1\n9007199254740993,1,1,1\n", "i.csv")
    assert read_events(ints, sensor_size=(4, 4), time_unit="ms").events["t"].tolist() == [
        7000, 9007199254740993000]
    assert read_events(ints, sensor_size=(4, 4), time_unit="ns").events["t"].tolist() == [
        0, 9007199254740]
    assert read_events(ints, sensor_size=(4, 4), time_unit="us").events["t"].tolist() == [
        7, 9007199254740993]
    with pytest.raises(ValueError, match="time_unit must be one of"):
        read_events(ints, sensor_size=(4, 4), time_unit="h")
