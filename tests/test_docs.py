"""The documentation cannot drift from the results, and everything it (or the code) cites exists.

- the measured tables in README.md and docs/ are what benchmarks/docs_tables.py renders from
  benchmarks/results/*.json (its --check), and a planted change is caught;
- every relative link in README.md and docs/*.md points at an existing file (and heading);
- every document a tracked file cites by path exists in the repository, and nothing cites a
  design note outside it;
- docs/model.md keeps its numbered sections 1-9 (the code cites "docs/model.md section N").
"""

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
sys.path.insert(0, str(ROOT / "benchmarks"))

import docs_tables  # noqa: E402

PAGES = [ROOT / "README.md", *sorted(DOCS.glob("*.md"))]
LINK = re.compile(r"\]\(([^)\s]+)\)")


def tracked_text_files() -> list[Path]:
    out = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True,
                         check=True).stdout.split()
    return [ROOT / p for p in out if Path(p).suffix in {".py", ".md", ".toml", ".ipynb", ".txt",
                                                         ".cfg"} and (ROOT / p).is_file()]


def test_generated_tables_match_the_results(capsys):
    assert docs_tables.main(["--check"]) == 0, capsys.readouterr().out


def test_every_table_renderer_is_used():
    used = {m.group(2) for page in PAGES for m in docs_tables.BLOCK.finditer(page.read_text())}
    assert used == set(docs_tables.TABLES)


def test_a_drifted_table_is_caught(tmp_path):
    page = tmp_path / "integrators.md"
    text = (DOCS / "integrators.md").read_text()
    drifted = re.sub(r"(<!-- table:integrators-stability -->\n.*?\| paper \| euler \| )[^|]+",
                     r"\g<1>9.99e-09 ", text, count=1, flags=re.S)
    assert drifted != text
    page.write_text(drifted)
    assert docs_tables.main(["--check", str(page)]) == 1
    assert docs_tables.main([str(page)]) == 0  # rewriting it restores the results' numbers
    assert page.read_text() == text


def test_an_unknown_table_is_an_error(tmp_path):
    page = tmp_path / "x.md"
    page.write_text("<!-- table:no-such-table -->\n<!-- /table -->\n")
    with pytest.raises(SystemExit, match="unknown table"):
        docs_tables.main(["--check", str(page)])


def test_the_paper_table_lists_every_impact():
    """docs/paper-comparison.md's "later impacts" row showed 3 of the default run's 5 later
    impacts (benchmarks/paper_reproduction.py kept impacts 2-4): every jaxland column of
    paper_table.json lists each impact after the first, and the rendered row shows them all."""
    data = json.loads((ROOT / "benchmarks" / "results" / "paper_table.json").read_text())
    header, _, *rows = docs_tables.paper_table().splitlines()
    names = [c.strip() for c in header.strip("|").split("|")]
    cells = next([c.strip() for c in r.strip("|").split("|")] for r in rows
                 if r.startswith("| later impacts"))
    runs = [c for c in data if "n_impacts" in data[c]]
    assert len(runs) >= 2, list(data)
    for c in runs:
        later = data[c]["later_impacts_s"]
        assert len(later) == data[c]["n_impacts"] - 1, (c, later)
        cell = cells[names.index(docs_tables.PAPER_COLUMNS.get(c, c))]
        assert len(cell.split(", ")) == len(later), (c, cell)


@pytest.fixture(scope="module")
def summaries(tmp_path_factory) -> dict:
    """simulate's summary.json of a short landing (touchdown at 0.2 s), quarter and 3-D."""
    import jaxland as jl

    out = {}
    for model in ("quarter", "full"):
        path = tmp_path_factory.mktemp(model) / "summary.json"
        jl.simulate(t_end=0.25, model=model).to_json(path)
        out[model] = json.loads(path.read_text())
    return out


@pytest.mark.parametrize("model", ["quarter", "full"])
def test_formats_md_describes_every_key_of_simulates_summary(summaries, model):
    """summary.json wrote keys docs/formats.md never named (solver_ok, n_rejected_steps,
    smoothing, the foot's normal and tangential acceleration, the 3-D final_position_m ...):
    each top-level key is named, in backticks, in its section on simulate's folder."""
    text = (DOCS / "formats.md").read_text()
    section = text[text.index("**`jaxland simulate`**"):text.index("**`jaxland montecarlo`**")]
    named = {" ".join(span.split()) for span in re.findall(r"`([^`]+)`", section)}
    missing = [k for k in summaries[model] if k not in named]
    assert not missing, f"docs/formats.md does not describe summary.json's {missing}"


def _anchors(page: Path) -> set[str]:
    """GitHub's heading anchors: lower case, punctuation dropped, spaces to hyphens."""
    heads = re.findall(r"^#+\s+(.*)$", page.read_text(), re.M)
    return {re.sub(r"[^\w\- ]", "", h.strip().lower()).replace(" ", "-") for h in heads}


@pytest.mark.parametrize("page", PAGES, ids=[p.name for p in PAGES])
def test_relative_links_resolve(page):
    broken = []
    for target in LINK.findall(page.read_text()):
        if re.match(r"^[a-z]+:", target):
            continue  # http(s), mailto
        path, _, anchor = target.partition("#")
        dest = (page.parent / path).resolve() if path else page
        if not dest.exists():
            broken.append(target)
        elif anchor and dest.suffix == ".md" and anchor not in _anchors(dest):
            broken.append(target)
    assert not broken, f"{page.name}: broken links {broken}"


def test_model_sections_are_numbered_1_to_9():
    numbers = re.findall(r"^## (\d+)\. ", (DOCS / "model.md").read_text(), re.M)
    assert numbers == [str(i) for i in range(1, 10)]


def test_cited_documents_exist():
    """Paths of documents cited anywhere in the tracked sources exist; "docs/model.md section N"
    names an existing section; no file cites a design note kept outside the repository."""
    sections = set(re.findall(r"^## (\d+)\. ", (DOCS / "model.md").read_text(), re.M))
    readme_heads = {h.strip().lower() for h in
                    re.findall(r"^#+\s+(.*)$", (ROOT / "README.md").read_text(), re.M)}
    problems = []
    for path in tracked_text_files():
        if path.name == Path(__file__).name:
            continue  # this file's patterns are not citations
        text = path.read_text(errors="replace")
        rel = path.relative_to(ROOT)
        for m in re.finditer(r"(?<![\w/.])((?:docs|data|benchmarks)/[\w./-]+\.md)\b", text):
            if not (ROOT / m.group(1)).exists():
                problems.append(f"{rel}: cites {m.group(1)}, which does not exist")
        for m in re.finditer(r"README(?:'s)?(?: section)? \"([^\"]+)\"", text):
            if m.group(1).lower() not in readme_heads:
                problems.append(f"{rel}: cites README \"{m.group(1)}\", no such README section "
                                "(the reference moved to docs/, see docs/index.md)")
        for m in re.finditer(r"docs/model\.md,? section (\d+)", text):
            if m.group(1) not in sections:
                problems.append(f"{rel}: cites docs/model.md section {m.group(1)}")
        if re.search(r"DESIGN\.md|\.\./shared|/work/shared", text):
            problems.append(f"{rel}: cites a design note outside the repository (DESIGN.md); "
                            "cite docs/model.md section N instead")
    assert not problems, "\n".join(problems)
