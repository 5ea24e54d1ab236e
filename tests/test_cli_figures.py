import subprocess
import sys

import pytest
from PIL import Image

from mrchaos.cli.figures import main


def test_sheet_of_builtin_library(tmp_path):
    out = tmp_path / "lib.png"
    assert main(["sheet", "--out", str(out)]) == 0
    img = Image.open(out)
    assert img.size[0] > 1000 and img.size[1] > 400


def test_families_and_validate(capsys, mrchaos104):
    from tests.conftest import MRCHAOS104

    assert main(["families", str(MRCHAOS104)]) == 0
    text = capsys.readouterr().out
    assert "agreement:" in text and "pose-1 " in text


def test_bad_input_exit_codes(tmp_path, capsys):
    assert main(["validate", str(tmp_path / "nope.json")]) == 2
    err = capsys.readouterr().err
    assert "nope.json" in err and err.count("\n") == 1
    bad = tmp_path / "bad.json"
    bad.write_text('{"figures": [{"id": "q", "pieces": []}]}')
    assert main(["validate", str(bad)]) == 1
    assert "rejected q" in capsys.readouterr().err


def test_console_script_installed():
    r = subprocess.run([sys.executable, "-m", "mrchaos.cli.figures", "--help"], capture_output=True, text=True)
    assert r.returncode == 0 and "sheet" in r.stdout


def test_help_names_every_registered_piece_set(capsys):
    from mrchaos.figures.pieces import piece_set_names

    with pytest.raises(SystemExit):
        main(["chaos", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert all(name in text for name in piece_set_names())
