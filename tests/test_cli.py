"""The command line: the tour checks every scene against its closed form."""

import pytest

from constrained_jax.__main__ import main


def test_tour_passes(capsys):
    assert main(["tour"]) == 0
    out = capsys.readouterr().out
    assert "all checks passed" in out
    assert "FAIL" not in out
    assert "cylinder_volume(b=0.001, l=1000)" in out


def test_one_scene_with_parameters(capsys):
    assert main(["scene", "cylinder_volume", "--b", "2", "--l", "3"]) == 0
    assert "cylinder_volume(b=2, l=3)" in capsys.readouterr().out


def test_unknown_scene_is_an_error():
    with pytest.raises(SystemExit) as info:
        main(["scene", "no_such_scene"])
    assert info.value.code != 0
