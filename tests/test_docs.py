"""The documentation site builds with --strict: no broken link, missing page or stale API reference."""

import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.skipif(
    importlib.util.find_spec("mkdocs") is None or importlib.util.find_spec("mkdocstrings") is None,
    reason="the docs extra is not installed (pip install -e '.[docs]')",
)
def test_the_documentation_site_builds_strictly(tmp_path):
    env = dict(os.environ, NO_MKDOCS_2_WARNING="1")
    r = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")],
        cwd=ROOT,
        capture_output=True,
        text=True,
        env=env,
        timeout=600,
    )
    assert r.returncode == 0, r.stderr[-3000:]
    assert (tmp_path / "site" / "reference" / "index.html").exists()


def test_readme_is_short_and_links_into_the_docs():
    text = (ROOT / "README.md").read_text()
    assert len(text.splitlines()) <= 250
    for page in ("getting-started", "concepts", "training", "benchmark", "performance", "extending"):
        assert f"docs/{page}.md" in text, page
        assert (ROOT / "docs" / f"{page}.md").exists(), page


def test_every_result_table_is_regenerated_by_the_script_with_its_command():
    import re
    import shlex

    sys.path.insert(0, str(ROOT / "tools"))
    try:
        import regenerate_results as regen
    finally:
        sys.path.pop(0)
    results = ROOT / "docs" / "results"
    tables = sorted(p.name for p in results.iterdir() if p.is_dir()) if results.exists() else []
    assert tables, "no result tables under docs/results"
    for name in tables:
        assert name in regen.TABLES, f"docs/results/{name} is not made by tools/regenerate_results.py"
        recorded = [shlex.split(ln) for ln in (results / name / "command.txt").read_text().splitlines()]
        args = [a for c in recorded for a in c]
        figures_dir = next((a.rsplit("/", 1)[0] for a in args if a.endswith(".json")), "../shared/figures")
        assert recorded == regen.commands(name, figures_dir), name
        assert recorded[-1][0] == "mrchaos-bench", name
        for f in ("results.json", "results.md"):
            assert (results / name / f).stat().st_size > 0, (name, f)
    # The pages include the files (pymdownx.snippets), and only files that exist.
    included = set()
    for page in (ROOT / "docs").glob("*.md"):
        for path in re.findall(r'--8<-- "([^"]+)"', page.read_text()):
            assert (ROOT / path).exists(), (page.name, path)
            included.add(Path(path).parent.name)
    assert set(tables) <= included, f"tables no page shows: {set(tables) - included}"


def test_the_readme_table_i_is_the_committed_result_file():
    """The README cannot include a file, so its Table I is checked against the ones the site includes:
    the generalist's row (benched alone, as the main job does) and table1's."""
    import json
    import re

    data = {}
    for table in ("generalist", "table1"):
        data |= json.loads((ROOT / "docs" / "results" / table / "results.json").read_text())["policies"]
    families = ("Random", "H-Normal", "H-Hard", "H-Fiendish")
    checked = {}
    for line in (ROOT / "README.md").read_text().splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) != 6 or not line.startswith("| "):
            continue
        named = re.match(r"\**`([\w-]+)`", cells[0])
        key = named.group(1) if named else cells[0].split(" ")[0]
        if key not in data:
            continue
        for fam, cell in zip(families, cells[2:], strict=True):
            shown = [float(x) for x in re.findall(r"\d+\.\d", cell)]
            m = data[key]["families"][fam]
            want = [round(100 * m["rela"]["mean"], 1), round(100 * m["final"]["mean"], 1)]
            assert shown == want, f"README Table I, {key} on {fam}: {shown} against results.json's {want}"
        checked[key] = None
    assert set(checked) == set(data), f"README Table I lacks {set(data) - set(checked)}"
    assert next(iter(checked)) == "mrchaos-generalist", "README Table I must lead with the main job's policy"
