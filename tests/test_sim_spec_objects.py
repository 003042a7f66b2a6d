"""Sensor spec YAML and bench objects: round trips, validation, meshes, the fixture plate."""

from __future__ import annotations

import dataclasses
import os

import numpy as np
import pytest
import trimesh
import yaml

from collect.errors import InputError
from hw_mocks.bubble_sim import BubbleSim
from hw_mocks.objects import BUILTIN_OBJECTS, PLATE_GAP, PLATE_Z, fixture_plate, load_object
from hw_mocks.sensor_spec import SensorSpec, draw_sensor


def test_spec_yaml_round_trip(tmp_path):
    spec = draw_sensor(12, "dead-pixels")
    spec.to_yaml(tmp_path / "s.yaml")
    back = SensorSpec.from_yaml(tmp_path / "s.yaml")
    assert back == spec
    assert back.intrinsics() == {k: getattr(spec, k) for k in ("fx", "fy", "cx", "cy", "width", "height")}
    assert back.fps == 45.0 and len(back.camera_in_tcp) == 6
    assert -0.1 < back.camera_in_tcp[2] < -0.085


def test_spec_numbers_in_scientific_notation_and_text_that_looks_like_one(tmp_path):
    """The spec reads YAML with the bench's and the thresholds' loader (collect.yaml_files): 1e3 is
    a number (was: the text '1e3', refused by the whole-number field dot_seed), and text that
    looks like a number (serial 1e6) is written quoted, so that it reads back as text."""
    data = draw_sensor(2).to_dict()
    text = yaml.safe_dump(data).replace(f"dot_seed: {data['dot_seed']}", "dot_seed: 1e3")
    text = text.replace(f"leak_hpa_per_s: {data['leak_hpa_per_s']!r}", "leak_hpa_per_s: 4e-05")
    assert "dot_seed: 1e3" in text and "leak_hpa_per_s: 4e-05" in text
    path = tmp_path / "sci.yaml"
    path.write_text(text)
    spec = SensorSpec.from_yaml(path)
    assert spec.dot_seed == 1000 and isinstance(spec.dot_seed, int) and spec.leak_hpa_per_s == 4e-05
    spec.serial = "1e6"
    spec.to_yaml(path)
    assert "serial: '1e6'" in path.read_text()
    assert SensorSpec.from_yaml(path) == spec


def test_draw_sensor_is_deterministic_and_varied():
    assert draw_sensor(3) == draw_sensor(3)
    specs = [draw_sensor(s) for s in range(8)]
    for name in ("fx", "dome_height_m", "tension_n_per_m", "gauge_pressure_pa", "emitter_amplitude", "depth_noise_m"):
        values = [getattr(s, name) for s in specs]
        assert np.std(values) > 0.01 * np.mean(np.abs(values)), name
    assert draw_sensor(3, "leak").leak_hpa_per_s * 60 > 1.0
    assert draw_sensor(3, "no-dots").dot_coverage == 0.0
    with pytest.raises(InputError):
        draw_sensor(3, "melted")
    for seed in (-1, 10**100):  # the huge one's serial would not fit the pressure board's ID line
        with pytest.raises(InputError, match="sensor seed must be within 0..4294967295"):
            draw_sensor(seed)


@pytest.mark.parametrize(
    "edit, field",
    [
        (lambda d: d.pop("tension_n_per_m"), "tension_n_per_m"),
        (lambda d: d.update(fx=-5.0), "fx"),
        (lambda d: d.update(gas_volume_m3="lots"), "gas_volume_m3"),
        (lambda d: d.update(camera_in_tcp=[0, 0]), "camera_in_tcp"),
        (lambda d: d.update(camera_in_tcp=[0, 0, -0.093, 1e300, 0, 0]), "camera_in_tcp' rotation"),
        (lambda d: d.update(camera_in_tcp=[0, 0, -0.093, 3.1416, 0, 0]), "camera_in_tcp' rotation"),
        (lambda d: d.update(camera_in_tcp=[1.0, 0, -0.093, 0, 0, 0]), "camera_in_tcp' x, y"),
        # was: refused for fx and fy (0.1 mm behind the rim), or accepted inside the dome (5 % of it with depth)
        (lambda d: d.update(camera_in_tcp=[0, 0, -0.031, 0, 0, 0]), r"z = -0.031 m puts the camera 0.1 mm behind the "
                                                                    r"bubble's rim .* at least 10 mm behind it"),
        (lambda d: d.update(camera_in_tcp=[0, 0, -0.03, 0, 0, 0], dome_height_m=0.05),
         r"puts the camera 20.0 mm in front of the bubble's rim \(dome_height_m 0.05 m below the apex\)"),
        (lambda d: d.update(serial="SB-1\nX"), "serial"),
        (lambda d: d.update(serial="SB-é"), "serial"),
        (lambda d: d.update(serial="S" * 65), "serial"),
        (lambda d: d.update(dead_pixels=[[500, 3]]), "dead_pixels"),
        (lambda d: d.update(colour="red"), "colour"),
        # was: 1.7 taken as pixel 1; a serial written as a number taken as its text, 0042 as "34"
        (lambda d: d.update(dead_pixels=[[1.7, 2.9]]), "field 'dead_pixels' has a bad value"),
        # a number in quotes is text, as in every other file the tool reads (was: read as the number)
        (lambda d: d.update(fx=str(d["fx"])), r"field 'fx' has a bad value '\d+\.\d+'"),
        (lambda d: d.update(width="224"), "field 'width' has a bad value '224'"),
        (lambda d: d.update(camera_in_tcp=["0", 0, -0.093, 0, 0, 0]), "field 'camera_in_tcp' has a bad value"),
        (lambda d: d.update(serial=34), r"field 'serial' must be text, but YAML read it as 34; quote it exactly as "
                                        r"the file writes it \(serial: '\.\.\.'\)"),
        # a slipped decimal point: a 10-degree view (was: a physics grid 100 times as large, no end to a preview)
        (lambda d: d.update(fx=10 * d["fx"]), "field 'fx' = .* gives a field of view of 10.. degrees over 224 px"),
        (lambda d: d.update(fy=20.0), "field 'fy' = 20.0 px gives a field of view of 153.8 degrees over 172 px"),
    ],
)
def test_bad_spec_fields_name_the_field(tmp_path, edit, field):
    data = draw_sensor(1).to_dict()
    edit(data)
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(InputError, match=field):
        SensorSpec.from_yaml(path)


def test_bad_yaml_and_missing_file(tmp_path):
    path = tmp_path / "broken.yaml"
    path.write_text("serial: [unclosed\nfx: 1")
    with pytest.raises(InputError, match="not valid YAML: line"):
        SensorSpec.from_yaml(path)
    path.write_text(yaml.safe_dump(draw_sensor(1).to_dict()) + "fps: 30\n")
    with pytest.raises(InputError, match="not valid YAML: line .*, column 1: duplicate key 'fps'"):  # was: "bad YAML at line 40" alone
        SensorSpec.from_yaml(path)
    path.write_text("- just\n- a list\n")
    with pytest.raises(InputError, match="mapping"):
        SensorSpec.from_yaml(path)
    with pytest.raises(InputError, match="cannot read"):
        SensorSpec.from_yaml(tmp_path / "nope.yaml")
    good = yaml.safe_dump(draw_sensor(1).to_dict())
    path.write_text(good + "colour: red\n1: 2\n")  # keys of two types (was: a TypeError traceback from their sort)
    with pytest.raises(InputError, match="unknown field '1'"):
        SensorSpec.from_yaml(path)
    path.write_text("fx: " + "[" * 3000 + "]" * 3000 + "\n")  # was: a RecursionError traceback
    with pytest.raises(InputError, match="not valid YAML: its lists or mappings are nested too deeply$"):
        SensorSpec.from_yaml(path)
    path.write_text(good.replace("fps: 45.0", "fps: 3.9"))  # a frame every 0.26 s: was accepted, then a stalled camera
    with pytest.raises(InputError, match=r"field 'fps' = 3.9 is outside \[4.0, 240.0\]"):
        SensorSpec.from_yaml(path)
    path.write_text(good.replace("fps: 45.0", "fps: 4.0"))
    assert SensorSpec.from_yaml(path).fps == 4.0
    path.write_text(good.replace(f"serial: {draw_sensor(1).serial}", "serial: 0042"))  # was: read as the octal 34
    assert SensorSpec.from_yaml(path).serial == "0042"


def test_a_camera_that_spreads_the_rim_over_millions_of_pixels_is_refused():
    """A large image at a long focal length passes the field-of-view check (107 degrees) but would make a
    physics grid of 1.4 million cells, minutes per simulated frame."""
    spec = dataclasses.replace(draw_sensor(1), width=4096, height=4096, fx=1500.0, fy=1500.0, cx=2048.0, cy=2048.0)
    spec.validate()
    with pytest.raises(InputError, match=r"its camera \(fx 1500, fy 1500 px\) sees the bubble's rim over .* a physics "
                                         r"grid of \d+ cells \(at most 250000\); check fx and fy"):
        BubbleSim(spec, [])


def test_a_camera_that_sees_little_of_the_membrane_is_refused():
    """200 mm behind the apex the camera sees the membrane over 9 % of its image (was: rendered, and the
    preview of a camera that saw none of it printed numpy's warnings and "valid depth nan%")."""
    spec = dataclasses.replace(draw_sensor(1), camera_in_tcp=[0.0, 0.0, -0.2, 0.0, 0.0, 0.0])
    spec.validate()
    with pytest.raises(InputError, match=r"its camera sees the membrane over 9 % of its image \(at least 25 %\)"):
        BubbleSim(spec, [])


def test_builtin_objects_are_watertight_with_primitives():
    for name in BUILTIN_OBJECTS:
        obj = load_object(name)
        assert obj.mesh.is_watertight, name
        assert obj.mesh.bounds[0, 2] == pytest.approx(0.0, abs=1e-9)  # sits on the fixture
        assert len(obj.mesh_sha256) == 64
    mug = load_object("mug").primitive
    assert mug["type"] == "cylinder" and mug["radius"] == pytest.approx(0.041)
    top = load_object("mug").heightmap.heights.max()
    assert top == pytest.approx(mug["center"][2] + mug["radius"], abs=5e-4)


def test_mesh_files(tmp_path):
    good = trimesh.creation.box(extents=[0.03, 0.02, 0.01])
    good.apply_translation([0, 0, 0.005])
    good.export(tmp_path / "brick.stl")
    obj = load_object(tmp_path / "brick.stl")
    assert obj.name == "brick" and obj.mesh.is_watertight
    assert obj.heightmap.heights.max() == pytest.approx(0.01, abs=1e-6)

    open_box = trimesh.creation.box(extents=[0.03, 0.02, 0.01])
    open_box.update_faces(np.arange(len(open_box.faces)) != 0)
    open_box.export(tmp_path / "open.stl")
    with pytest.raises(InputError, match="not watertight"):
        load_object(tmp_path / "open.stl")
    stl = (tmp_path / "brick.stl").read_bytes()
    (tmp_path / "half.stl").write_bytes(stl[: len(stl) // 2])  # was: "ModuleNotFoundError: … charset_normalizer"
    with pytest.raises(InputError, match="half.stl: it is neither a binary STL file nor UTF-8 text"):
        load_object(tmp_path / "half.stl")
    (tmp_path / "junk.ply").write_bytes(b"\x00garbage\xff" * 10)
    with pytest.raises(InputError):
        load_object(tmp_path / "junk.ply")
    with pytest.raises(InputError, match="not found"):
        load_object(tmp_path / "missing.obj")
    with pytest.raises(InputError, match="unknown object"):
        load_object("teapot")


def _brick(tmp_path, name, shift=(0.0, 0.0, 0.005), extents=(0.03, 0.02, 0.01), edit=None):
    """A box mesh file ``name`` in ``tmp_path``, moved by ``shift`` (m) and passed through ``edit``."""
    mesh = trimesh.creation.box(extents=extents)
    mesh.apply_translation(shift)
    if edit is not None:
        mesh = edit(mesh)
    mesh.export(tmp_path / name)
    return tmp_path / name


@pytest.mark.parametrize("name, shift, message", [
    ("floating.stl", (0.0, 0.0, 5.0), r"spans x -0.015..0.015, y -0.01..0.01, z 4.995..5.005 m: its origin must lie "
                                      r"within the part"),  # was: pressed 5 m above the plate
    ("aside.stl", (3.0, 3.0, 0.005), r"spans x 2.985..3.015"),  # was: a pose check 50 mm off, turned about a far origin
])
def test_a_meshs_origin_must_lie_within_it(tmp_path, name, shift, message):
    with pytest.raises(InputError, match=message):
        load_object(_brick(tmp_path, name, shift))


def test_a_mesh_exported_around_its_centre_rests_on_the_plate(tmp_path):
    """``trimesh.creation``'s parts are centred on their origin: was refused ("its origin must be on
    the fixture"); rests on the plate by its lowest point, as the same part standing on its origin."""
    centred, standing = (fixture_plate([load_object(_brick(tmp_path, name, shift))])[0]
                         for name, shift in (("centred.stl", (0.0, 0.0, 0.0)), ("standing.stl", (0.0, 0.0, 0.005))))
    assert centred.fixture_pose[2] == pytest.approx(PLATE_Z + 0.005)
    np.testing.assert_allclose(centred.bounds_base(), standing.bounds_base(), atol=1e-9)
    assert centred.bounds_base()[0][2] == pytest.approx(PLATE_Z)
    # its height field too, the cells beside it included (was: their floor at z = -0.05 m of the object
    # frame, 45 mm below the plate beside a 1 cm part standing on its origin, 50 mm beside this one)
    np.testing.assert_allclose(centred.heightmap.heights + 0.005, standing.heightmap.heights, atol=1e-6)


def test_the_commission_benchmarks_unseen_meshes_stand_on_their_origin(tmp_path):
    """``bench_commission`` presses them through ``bubble collect``; its capsule floated 18 mm above
    the plate, and the benchmark stopped with this module's error once meshes had to stand on it."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from benchmarks.bench_commission import unseen_meshes

    for path in unseen_meshes(tmp_path):
        assert load_object(path).mesh.bounds[0][2] == pytest.approx(0.0, abs=1e-6), path


def test_mesh_files_that_are_repaired_or_named_wrong(tmp_path):
    inside_out = load_object(_brick(tmp_path, "inside_out.stl", edit=lambda m: trimesh.Trimesh(m.vertices, m.faces[:, ::-1])))
    assert inside_out.mesh.volume == pytest.approx(6e-6)  # was: taken as is, a negative volume for the pose check's SDF
    doubled = load_object(_brick(tmp_path, "doubled.stl", edit=lambda m: trimesh.Trimesh(
        m.vertices, np.vstack([m.faces, m.faces, [[0, 0, 1]]]), process=False)))  # each face twice, one of zero area
    assert len(doubled.mesh.faces) == 12 and doubled.mesh.is_watertight  # was: "is not watertight"
    five_mm = load_object(_brick(tmp_path, "five.stl", shift=(0, 0, 0.0025), extents=(0.005, 0.005, 0.005)))
    assert five_mm.mesh.extents.max() < 0.005  # float32's rounding, was: "is 0.005 m across; expected 5 mm to 0.5 m"
    nan = _brick(tmp_path, "nan.ply", edit=lambda m: trimesh.Trimesh(np.where(np.arange(8)[:, None] == 3, np.nan, m.vertices),
                                                                     m.faces, process=False))
    with pytest.raises(InputError, match="has non-finite vertices"):  # was: "is not watertight"
        load_object(nan)
    with pytest.raises(InputError, match=r"mug.stl would be named 'mug', as the built-in object; rename the file"):
        load_object(_brick(tmp_path, "mug.stl"))
    os.mkfifo(tmp_path / "pipe.stl")
    with pytest.raises(InputError, match="pipe.stl is not a regular file"):  # was: "mesh file not found"
        load_object(tmp_path / "pipe.stl")
    latin1 = _brick(tmp_path, os.fsdecode(b"caf\xe9.stl"))  # a name of Latin-1 bytes, as argv decodes it
    with pytest.raises(InputError) as info:  # was: "UnicodeEncodeError: 'utf-8' codec can't encode character"
        load_object(latin1)
    assert str(info.value) == f"mesh {latin1}: its file name is not UTF-8 text, and names the object; rename the file"
    escape = _brick(tmp_path, "cup\x1b[31m\nrow.stl")  # was: recorded, and `bubble info` printed its row in two, coloured
    with pytest.raises(InputError) as info:
        load_object(escape)
    assert str(info.value) == (f"mesh {str(escape)!r}: its file name holds control characters (a line break, a tab, a "
                               "terminal escape), and names the object; rename the file")
    assert "\x1b" not in str(info.value) and "\n" not in str(info.value)
    for text in ("tasse à café", "cup\u00a0big", "cup\u202fbig", "カップ\u3000大", "👩\u200d🔧"):  # spaces of any script, joiners
        assert load_object(_brick(tmp_path, f"{text}.stl")).name == text
    with pytest.raises(InputError, match="holds control characters"):  # a right-to-left override reorders the line
        load_object(_brick(tmp_path, "cup\u202egnp.stl"))


def test_a_mesh_in_kilometres_is_refused_by_its_size_without_a_warning(tmp_path):
    """Was: 1e30 m coordinates passed to trimesh's vertex merge, which printed a RuntimeWarning (cast
    overflow) above the error line, and that line said "not watertight"."""
    import warnings

    huge = _brick(tmp_path, "huge.stl", edit=lambda m: trimesh.Trimesh(m.vertices * 1e30, m.faces, process=False))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(InputError, match=r"huge.stl is 3e\+28 m across; expected metres \(5 mm to 0.5 m\)"):
            load_object(huge)


def test_objects_longer_than_the_plate_are_refused(tmp_path):
    """Was: six 0.45 m parts placed along 2.7 m of 'plate', the arm sent 1.35 m to either side."""
    wide = [load_object(_brick(tmp_path, f"slab{i}.stl", extents=(0.05, 0.3, 0.01))) for i in range(3)]
    assert len(fixture_plate(wide[:2])) == 2  # 0.69 m
    with pytest.raises(InputError, match=r"the objects take 1.080 m of the fixture plate in a row \(90 mm apart\), "
                                         r"longer than its 1 m; press fewer or smaller objects in one session"):
        fixture_plate(wide)


def test_fixture_plate_spacing_and_surface_points():
    objs = fixture_plate([load_object(n) for n in BUILTIN_OBJECTS])
    boxes = [o.bounds_base() for o in objs]
    for a, b in zip(boxes, boxes[1:]):
        assert b[0, 1] - a[1, 1] == pytest.approx(PLATE_GAP)
    for o, bb in zip(objs, boxes):
        assert -0.32 < bb[0, 1] and bb[1, 1] < 0.32
        assert bb[0, 2] == pytest.approx(0.0, abs=1e-9)
        assert 0.3 < bb.mean(axis=0)[0] < 0.6
        pts, normals = o.top_surface_points(50, np.random.default_rng(0))
        assert pts.shape == normals.shape == (50, 3)
        assert (normals[:, 2] > np.cos(np.radians(25.5))).all()
        t = o.object_to_base()
        local = (pts - t[:3, 3]) @ t[:3, :3]
        assert np.allclose(o.heightmap.sample(local[:, 0], local[:, 1]), local[:, 2], atol=1e-6)
