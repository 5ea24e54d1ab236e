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
        recorded = shlex.split((results / name / "command.txt").read_text())
        figures_dir = next((a.rsplit("/", 1)[0] for a in recorded if a.endswith(".json")), "../shared/figures")
        assert recorded == regen.command(name, figures_dir), name
        for f in ("results.json", "results.md"):
            assert (results / name / f).stat().st_size > 0, (name, f)
    # The pages include the files (pymdownx.snippets), and only files that exist.
    included = set()
    for page in (ROOT / "docs").glob("*.md"):
        for path in re.findall(r'--8<-- "([^"]+)"', page.read_text()):
            assert (ROOT / path).exists(), (page.name, path)
            included.add(Path(path).parent.name)
    assert set(tables) <= included, f"tables no page shows: {set(tables) - included}"
