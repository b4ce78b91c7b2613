"""Every relative link in README.md and docs/ resolves; every docs path the code names exists."""

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")
DOC_PATH = re.compile(r"docs/[\w./-]+\.md")
# Pages the other branches of this release add (README links them already). A link to one is
# not checked while the page is absent; once merged it is checked like any other. Remove the
# names here after the merge.
COMING: set[str] = set()  # pages other work will add: links to them skip while absent


def pages():
    return [ROOT / "README.md", ROOT / "CHANGELOG.md", *sorted((ROOT / "docs").rglob("*.md"))]


def slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"[^\w\- ]", "", heading.strip().lower())
    return text.replace(" ", "-")


def anchors(page: Path) -> set[str]:
    text = re.sub(r"```.*?```", "", page.read_text(encoding="utf-8"), flags=re.S)
    return {slug(m.group(1)) for m in re.finditer(r"^#+ (.*)$", text, flags=re.M)}


def links(page: Path):
    text = re.sub(r"```.*?```", "", page.read_text(encoding="utf-8"), flags=re.S)
    for m in LINK.finditer(text):
        target = m.group(1)
        if not re.match(r"^[a-z]+:", target):  # http:, https:, mailto:
            yield target


def test_every_relative_link_resolves():
    broken = []
    for page in pages():
        for target in links(page):
            path, _, anchor = target.partition("#")
            dest = (page.parent / path).resolve() if path else page
            coming = str(dest.relative_to(ROOT)) in COMING if dest.is_relative_to(ROOT) else False
            if coming and not dest.exists():
                continue
            if not dest.exists():
                broken.append(f"{page.relative_to(ROOT)}: {target}")
            elif anchor and dest.suffix == ".md" and anchor not in anchors(dest):
                broken.append(f"{page.relative_to(ROOT)}: {target} (no such heading)")
    assert not broken, "\n".join(broken)


def test_docs_paths_named_in_code_exist():
    missing = []
    for folder in ("torchseq", "benchmarks", "experiments", "tests"):
        for py in (ROOT / folder).rglob("*.py"):
            for path in DOC_PATH.findall(py.read_text(encoding="utf-8")):
                if not (ROOT / path).exists():
                    missing.append(f"{py.relative_to(ROOT)}: {path}")
    assert not missing, "\n".join(missing)


def test_generated_reference_pages_are_up_to_date():
    import importlib.util

    spec = importlib.util.spec_from_file_location("docs_generate", ROOT / "docs" / "generate.py")
    generate = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(generate)
    stale = [str(path.relative_to(ROOT)) for path, text in generate.pages().items()
             if not path.exists() or path.read_text(encoding="utf-8") != text]
    assert not stale, f"out of date: {stale}; run python docs/generate.py"


def test_no_tracker_numbers_in_docs_or_code():
    # a reference names the change or the results section it means, not a ticket number
    ticket = re.compile(r"issues? ?#?\d+", re.I)
    files = [*pages(), *sorted((ROOT / "torchseq").rglob("*.py"))]
    said = [f"{f.relative_to(ROOT)}: {m.group(0)}" for f in files
            for m in ticket.finditer(f.read_text(encoding="utf-8"))]
    assert not said, said[:10]
