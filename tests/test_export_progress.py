"""The export's progress on stderr: bars on a terminal, plain lines (no carriage returns) else."""

import io

from torchseq.export.progress import ExportProgress


class _Tty(io.StringIO):
    def isatty(self):
        return True


def test_plain_lines_when_not_a_terminal():
    buf = io.StringIO()
    p = ExportProgress(file=buf)
    with p.step("NIR: norse", 16, "steps of 32 streams") as update:
        for i in range(16):
            update(i + 1)
    with p.step("NIR: hardware budget"):
        pass
    text = buf.getvalue()
    assert "\r" not in text
    lines = text.splitlines()
    assert lines[0] == "export: NIR: norse (16 steps of 32 streams) ..."
    assert lines[1].startswith("export: NIR: norse: done in ") and lines[1].endswith(" s")
    assert lines[2] == "export: NIR: hardware budget ..." and len(lines) == 4


def test_bars_on_a_terminal_and_nothing_when_disabled():
    tty = _Tty()
    with ExportProgress(file=tty).step("NIR: snntorch", 5) as update:
        for i in range(5):
            update(i + 1)
    assert "export: NIR: snntorch" in tty.getvalue() and "5/5" in tty.getvalue()
    quiet = io.StringIO()
    with ExportProgress(enabled=False, file=quiet).step("x", 3) as update:
        update(3)
    assert quiet.getvalue() == ""
