"""The command lines' own contract: any bad input is one ``prog: error:`` line and exit 2.

Every case runs the real script (``eval.py`` / ``train.py`` executed as ``__main__`` with
its own argv, in one child process to keep the suite fast). The cases are the hostile
arguments that printed a traceback, ran out of memory or exited 0 with NaN results before.
"""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import coarse_units_expected

ROOT = Path(__file__).resolve().parents[1]

DRIVER = r"""
import contextlib, io, json, runpy, sys
results = []
for script, args in json.loads(sys.stdin.read()):
    err = io.StringIO()
    sys.argv = [script, *args]
    code = None
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            runpy.run_path(script, run_name="__main__")
        except SystemExit as e:
            code = e.code
        except BaseException as e:
            code = "raised " + type(e).__name__ + ": " + str(e)[:200]
    results.append([code, err.getvalue()])
print(json.dumps(results))
"""


def run_cases(cases):
    """Run ``[(script, args), ...]`` as ``__main__``; return ``[(exit code, stderr), ...]``."""
    payload = json.dumps([[str(ROOT / s), [*a, "--no-progress"]] for s, a in cases])
    proc = subprocess.run([sys.executable, "-c", DRIVER], input=payload, capture_output=True,
                          text=True, cwd=ROOT, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


def huge_npy(path, shape, descr="<f4"):
    """An .npy whose header declares ``shape`` but holds only a few bytes."""
    with open(path, "wb") as f:
        np.lib.format.write_array_header_1_0(
            f, {"descr": descr, "fortran_order": False, "shape": shape})
        f.write(b"\0" * 64)


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    from torchseq.neural import NeuralConfig, NeuralSeqSLAM

    d = tmp_path_factory.mktemp("hostile")
    frames = np.random.default_rng(0).integers(0, 255, (30, 32, 64)).astype(np.uint8)
    np.save(d / "frames.npy", frames)
    np.savez(d / "zip.npz", a=np.eye(30))
    (d / "zip.npz").rename(d / "zip_gt.npy")  # a zip named .npy
    structured = np.zeros((30, 32, 64), dtype=[("a", "<f4"), ("b", "<i2")])
    np.savez(d / "structured.npz", frames=structured)
    (d / "corrupt.npz").write_bytes(b"PK\x03\x04" + b"\x01" * 200)
    huge_npy(d / "huge_frames.npy", (10 ** 12, 64, 64))
    huge_npy(d / "huge_gt.npy", (30, 10 ** 13), "|u1")
    model = NeuralSeqSLAM(NeuralConfig(unit_search="off", hidden=64, n_output=10))
    with coarse_units_expected():  # a small model: units of several frames
        model.fit(torch.from_numpy(frames).float())
    model.save(d / "good.pt")
    blob = torch.load(d / "good.pt", weights_only=True)
    blob["config"]["hidden"] = "64"
    torch.save(blob, d / "string_hidden.pt")
    blob["config"]["hidden"] = 64
    blob["config"]["input_size"] = [24]
    torch.save(blob, d / "short_input.pt")
    return d


def eval_cases(d):
    data = ["--reference", str(d / "frames.npy"), "--query", str(d / "frames.npy")]
    return [
        (["--engine", "seqslam", *data, "--ground-truth", str(d / "zip_gt.npy")], "zip"),
        (["--engine", "neural", *data, "--checkpoint", str(d / "string_hidden.pt")],
         "checkpoint"),
        (["--engine", "neural", *data, "--checkpoint", str(d / "short_input.pt")],
         "checkpoint"),
        (["--reference", str(d / "structured.npz"), "--query", str(d / "frames.npy")],
         "numeric"),
        (["--reference", str(d / "corrupt.npz"), "--query", str(d / "frames.npy")],
         "corrupt.npz"),
        (["--reference", str(d / "huge_frames.npy"), "--query", str(d / "frames.npy")],
         "huge_frames.npy"),
        (["--engine", "seqslam", *data, "--ground-truth", str(d / "huge_gt.npy")],
         "huge_gt.npy"),
        (["--window-ms", "inf"], "--window-ms"),
        (["--window-ms", "1e306"], "--window-ms"),
        (["--window-ms", "nan"], "--window-ms"),
        (["--demo-frames", "100000000000"], "--demo-frames"),
        (["--demo-speed", "1e-9"], "--demo-speed"),
        (["--ds", "10000000000"], "--ds"),
        (["--tolerance", "nan"], "--tolerance"),
        (["--vmax", "inf"], "argument --vmax: must be a finite"),  # main: "vmin must be > 0"
        (["--vmin", "-1"], "--vmin"),
        (["--target-precision", "2"], "--target-precision"),
        (["--image-size", "0x64"], "--image-size"),
        (["--frame-size", "99999999x2"], "--frame-size"),
        (["--neural-hidden", "100000000"], "--neural-hidden"),
        (["--neural-eps", "nan"], "--neural-eps"),
        (["--seed", "-1"], "--seed"),
        (["--bogus-flag", "1"], "unrecognized"),
        (["--sweep", "nothing=1,2"], "--sweep"),
        (["--sweep", "ds=10,abc"], "--ds"),
        (["--window-anchor", "sometime"], "--window-anchor"),
        (["--checkpoint", str(d / "good.pt"), "--neural-hidden", "128"], "--neural-"),
        (["--checkpoint", str(d / "good.pt"), "--neural-seed", "7"], "--neural-"),
        # settings the run would silently ignore
        (["--engine", "seqslam", "--neural-hidden", "128", "--neural-seed", "3"],
         "--neural-hidden, --neural-seed have no effect with --engine seqslam"),
        (["--engine", "seqslam", "--checkpoint", str(d / "good.pt")],
         "--checkpoint has no effect with --engine seqslam"),
        (["--engine", "neural", "--ds", "20", "--preset", "events"],
         "--ds, --preset have no effect with --engine neural"),
        ([*data, "--demo-frames", "50"], "--demo-frames shapes the built-in demo route"),
        ([*data, "--target-precision", "0.9"], "this run has none (--ground-truth or"),
        (["--sweep", "engine=both,seqslam", "--neural-n-output", "50"],
         "--neural-n-output has no effect with --engine seqslam"),
    ]


def train_cases(d):
    return [
        (["--neural-eps", "nan"], "--neural-eps"),
        (["--neural-ring-gain", "nan"], "--neural-ring-gain"),
        (["--neural-ring-stay", "nan"], "--neural-ring-stay"),
        (["--neural-ring-spread-decay", "inf"], "--neural-ring-spread-decay"),
        (["--neural-hidden", "abc"], "--neural-hidden"),
        (["--neural-hidden", str(2 ** 40)], "--neural-hidden must be in 1..1048576"),
        (["--demo-frames", "100000000000"], "--demo-frames"),
        (["--reference", str(d / "huge_frames.npy")], "huge_frames.npy"),
        (["--window-ms", "-5"], "--window-ms"),
        (["--export-frame-size", "axb"], "size"),
        (["--export-query", "q.npy", "--export-frame-size", "48x64"],
         "--export-query, --export-frame-size set up the export, which runs only with --export"),
    ]


@pytest.mark.slow  # an end-to-end run (CI's slow pass runs it)
def test_hostile_arguments_are_one_line_and_exit_2(files, tmp_path):
    cases = [("eval.py", [*a, "--out", str(tmp_path / f"e{i}")], m)
             for i, (a, m) in enumerate(eval_cases(files))]
    cases += [("train.py", [*a, "--out", str(tmp_path / f"t{i}")], m)
              for i, (a, m) in enumerate(train_cases(files))]
    results = run_cases([(s, a) for s, a, _ in cases])
    bad = []
    for (script, args, must), (code, err) in zip(cases, results):
        lines = err.strip().splitlines()
        ok = (code == 2 and len(lines) == 1 and lines[0].startswith(f"{script}: error: ")
              and must in lines[0])
        if not ok:
            bad.append(f"{script} {' '.join(args[:4])}...: exit {code}, stderr {err[-300:]!r}")
    assert not bad, "\n".join(bad)
    # nothing was written for any refused run
    assert not any((tmp_path / p).exists() and any((tmp_path / p).iterdir())
                   for p in [f"e{i}" for i in range(len(eval_cases(files)))])


@pytest.mark.slow  # an end-to-end run (CI's slow pass runs it)
def test_real_subprocess_of_the_script(tmp_path):
    proc = subprocess.run([sys.executable, str(ROOT / "eval.py"), "--tolerance", "nan",
                           "--out", str(tmp_path / "o")], capture_output=True, text=True,
                          cwd=ROOT, timeout=120)
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [
        "eval.py: error: argument --tolerance: must be a finite number, got 'nan'"]
