"""`bubble sim new-sensor` and `bubble sim preview`, including bad input (exit 2, one line)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from calibrate.cli import main
from hw_mocks.sensor_spec import SensorSpec


def test_new_sensor_and_preview(tmp_path, capsys):
    spec_path = tmp_path / "spec.yaml"
    assert main(["sim", "new-sensor", "--seed", "21", "--defect", "leak", "--out", str(spec_path)]) == 0
    spec = SensorSpec.from_yaml(spec_path)
    assert spec.defect == "leak" and spec.leak_hpa_per_s > 0
    png = tmp_path / "p.png"
    assert main(["sim", "preview", "--sensor", str(spec_path), "--object", "box", "--press-mm", "4", "--out", str(png)]) == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    out = capsys.readouterr().out
    assert "pressure" in out and "force" in out
    sphere = tmp_path / "cup$^$.stl"  # its name is text in the figure (was: read as math, a ValueError traceback)
    trimesh.creation.icosphere(radius=0.02).apply_translation([0, 0, 0.02]).export(sphere)
    assert main(["sim", "preview", "--sensor", str(spec_path), "--object", str(sphere), "--press-mm", "3", "--out",
                 str(png)]) == 0


def _fails_with_one_line(capsys, argv, needle):
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and needle in err and "Traceback" not in err


def test_bad_input_exits_2(tmp_path, capsys):
    spec_path = tmp_path / "spec.yaml"
    main(["sim", "new-sensor", "--seed", "1", "--out", str(spec_path)])
    capsys.readouterr()
    bad = tmp_path / "bad.yaml"
    bad.write_text("fx: [1, 2\n")
    png = str(tmp_path / "x.png")
    _fails_with_one_line(capsys, ["sim", "preview", "--sensor", str(bad), "--object", "mug", "--out", png], "is not valid YAML: line")
    _fails_with_one_line(capsys, ["sim", "preview", "--sensor", str(spec_path), "--object", "teapot", "--out", png], "unknown object")
    holey = trimesh.creation.icosphere(radius=0.02)
    holey.update_faces(np.arange(len(holey.faces)) > 3)
    holey.export(tmp_path / "holey.stl")
    _fails_with_one_line(
        capsys, ["sim", "preview", "--sensor", str(spec_path), "--object", str(tmp_path / "holey.stl"), "--out", png], "watertight"
    )
    for deep in ("80", "12.5"):  # 12.5: beyond the membrane model's range (was: accepted up to 30 mm, 2.6 kN)
        _fails_with_one_line(capsys, ["sim", "preview", "--sensor", str(spec_path), "--object", "mug", "--press-mm", deep,
                                      "--out", png], f"--press-mm must be within [0, 12] (the simulated membrane's range), got {deep}")
    shallow = tmp_path / "shallow.yaml"  # a 5 mm dome: a 20 mm press went through it (was: 8.7 kN, exit 0)
    shallow.write_text(spec_path.read_text().replace(f"dome_height_m: {SensorSpec.from_yaml(spec_path).dome_height_m}",
                                                     "dome_height_m: 0.005"))
    assert SensorSpec.from_yaml(shallow).dome_height_m == 0.005
    _fails_with_one_line(capsys, ["sim", "preview", "--sensor", str(shallow), "--object", "mug", "--press-mm", "8",
                                  "--out", png], "--press-mm 8 is deeper than the sensor's dome is high (5.0 mm, its travel)")
    _fails_with_one_line(capsys, ["sim", "new-sensor", "--seed", "-3", "--out", str(tmp_path / "n.yaml")], "seed")
    spec_text = spec_path.read_text()
    _fails_with_one_line(capsys, ["sim", "new-sensor", "--seed", "2", "--out", str(spec_path)], "already exists")
    assert spec_path.read_text() == spec_text  # the spec a recording was made with is never replaced
    # the same command again finds its own spec there, and an empty placeholder holds none (was: refused)
    assert main(["sim", "new-sensor", "--seed", "1", "--out", str(spec_path)]) == 0 and spec_path.read_text() == spec_text
    placeholder = tmp_path / "placeholder.yaml"
    placeholder.touch()
    assert main(["sim", "new-sensor", "--seed", "1", "--out", str(placeholder)]) == 0
    assert placeholder.read_text() == spec_text


def test_sim_help_names_the_subcommands_and_the_press_default(capsys):
    """Was: "the following arguments are required: sim_command", and --press-mm without its default."""
    with pytest.raises(SystemExit) as refused:
        main(["sim"])
    assert refused.value.code == 2
    assert capsys.readouterr().err == "bubble: error: the following arguments are required: {new-sensor,preview}\n"
    with pytest.raises(SystemExit) as done:
        main(["sim", "preview", "--help"])
    assert done.value.code == 0
    assert "(mm; default 5)" in " ".join(capsys.readouterr().out.split())
