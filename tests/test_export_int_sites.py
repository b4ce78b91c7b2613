"""The integer step is spelled out in two files only: its torch definition and its NumPy kernels.

A *site* is a function or method of ``torchseq/export`` whose own code (docstring and
comments aside) spells out an operation of the integer step: a rounding quotient, an integer
square root, a k-WTA, a gather of the stored index lists, the read-out's interpolation, the
cohort sums, the speed fit's denominator or an int8 GEMM. The runtimes, the step module and
the graph call the stage functions of ``int_functional.py`` instead, so a second copy of a
stage turns this test red. ``python tests/test_export_int_sites.py`` prints the count per
file (run it in an older checkout to compare: 21 sites in 5 files before the stage functions,
23 in 3 files after).
"""

import ast
import re
from pathlib import Path

import torchseq

EXPORT = Path(torchseq.__file__).parent / "export"
OPERATION = re.compile(
    r"(?<![.\w])(round_div|isqrt|kwta_(code|numpy|int)|within_unit|cohort_sums|velocity_den)\("
    r"|_CohortSums\.apply|_SparseCore\.apply|Int8Linear\.create"
    r"|ring_cols\]|\[:, cols\]|\[c\] \* v|l1_cols\]|l3_cols\]|l3_t\[")
# the definition (torch), the NumPy kernels, and the typed stages' bound check (check_fits)
ALLOWED = {"int_functional.py", "int_kernels.py", "int_stages.py"}


def sites(folder: Path = EXPORT) -> dict[str, list[str]]:
    """``{file name: [function names]}`` of the functions that spell out a step operation."""
    out = {}
    for path in sorted(folder.glob("*.py")):
        src = path.read_text()
        lines = src.splitlines()
        found = []
        for node in ast.walk(ast.parse(src)):
            if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            body = node.body[1:] if ast.get_docstring(node) else node.body
            code = [re.sub(r"#.*", "", lines[i - 1]) for stmt in body
                    for i in range(stmt.lineno, stmt.end_lineno + 1)]
            if any(OPERATION.search(line) for line in code):
                found.append(node.name)
        if found:
            out[path.name] = found
    return out


def test_the_counter_sees_a_spelled_out_stage(tmp_path):
    (tmp_path / "copy.py").write_text(
        "def ring(state, g):\n    '''Uses round_div(a, b) in its docstring only.'''\n"
        "    # round_div(x) in a comment\n    return round_div(state[:, cols].sum(-1), 2) + g\n"
        "def fine(x):\n    return F.round_div(x, 2)\n")
    assert sites(tmp_path) == {"copy.py": ["ring"]}


def test_the_step_is_spelled_out_only_in_its_definition_and_kernels():
    found = sites()
    assert set(found) <= ALLOWED, {f: found[f] for f in set(found) - ALLOWED}
    assert found["int_stages.py"] == ["check_fits"]
    # every stage has its torch body and its NumPy kernel
    assert len(found["int_functional.py"]) >= 9 and len(found["int_kernels.py"]) >= 9


if __name__ == "__main__":
    found = sites()
    for name, funcs in found.items():
        print(f"torchseq/export/{name}: {len(funcs)}  {' '.join(funcs)}")
    print(f"{sum(map(len, found.values()))} sites in {len(found)} files")
