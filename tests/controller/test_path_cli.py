"""``pfma path`` and ``pfma controller --record/--play`` on the simulated rack."""

from tools.cli import main


def test_path_cli_new_edit_show_delete(tmp_path, capsys):
    d = ["path", "--dir", str(tmp_path)]
    assert main(d + ["new", "sq", "--point", "1.5,0,-0.3", "--point", "1.6,0,-0.3"]) == 0
    assert main(d + ["edit", "sq", "--insert", "1", "--pos", "1.55,0.01,-0.3", "--speed", "all", "--v-lin", "0.02"]) == 0
    assert main(d + ["show", "sq", "--plan"]) == 0
    out = capsys.readouterr().out
    assert "path sq (id 1, revision 2, 3 points" in out and "0.02 m/s" in out and "playback plan: 3 segments" in out
    assert main(d + ["edit", "sq", "--move", "7", "--pos", "0,0,0"]) == 1
    assert "point 7 does not exist (3 points)" in capsys.readouterr().err
    assert main(d + ["delete", "sq"]) == 0
    assert main(d + ["list"]) == 0
    assert "no paths in" in capsys.readouterr().out


def test_controller_records_and_plays_back_on_the_simulated_rack(tmp_path, capsys):
    base = ["controller", "--sim", "--wm", "none", "--power-up", "--path-dir", str(tmp_path), "--messages", "0"]
    assert main(base + ["--demo-stick", "--record", "demo", "--teach-every", "1", "--duration", "3"]) == 0
    out = capsys.readouterr().out
    assert "recording into path demo (id 1)" in out and "(OK)" in out
    assert main(base + ["--play", "demo", "--duration", "10"]) == 0
    assert "path demo: playback ended (OK)" in capsys.readouterr().out
