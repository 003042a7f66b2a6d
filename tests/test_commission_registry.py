"""Sensor registry: registration, history, listing, location."""

import json

import numpy as np
import pytest

from calibrate.sensor_registry import SensorRegistry, default_registry_dir
from collect.errors import InputError

INTR = {"fx": 120.0, "fy": 120.0, "cx": 111.5, "cy": 85.5, "width": 224, "height": 172}


def _model_dir(tmp_path, tag):
    d = tmp_path / f"model-{tag}"
    d.mkdir()
    (d / "model.json").write_text(json.dumps({"tag": tag}))
    return d


def test_accepted_then_rejected_keeps_accepted_model(tmp_path):
    reg = SensorRegistry(tmp_path / "reg")
    ref = {"depth_m": np.full((4, 5), 0.09, np.float32), "ir": np.ones((4, 5), np.float32)}
    acc = {"accepted": True, "a1": 0.97, "abs_rel": 0.01, "rmse": 0.0008, "checks": []}
    p1 = reg.register(
        "SB-1", accepted=True, run_dir=tmp_path / "run1", intrinsics=INTR, camera_in_tcp=[0, 0, -0.093, 0, 0, 0],
        simulated=True, acceptance=acc, model_dir=_model_dir(tmp_path, "a"), reference=ref,
    )
    assert p1.status == "accepted" and p1.model_dir is not None
    assert json.loads((p1.model_dir / "model.json").read_text())["tag"] == "a"
    rej = {"accepted": False, "checks": []}
    p2 = reg.register(
        "SB-1", accepted=False, run_dir=tmp_path / "run2", intrinsics=INTR, camera_in_tcp=None, simulated=True,
        acceptance=rej, reason="leak", model_dir=_model_dir(tmp_path, "b"),
    )
    assert p2.status == "rejected" and p2.data["last_reason"] == "leak"
    assert json.loads((p2.model_dir / "model.json").read_text())["tag"] == "a"
    assert [h["accepted"] for h in p2.history] == [True, False]
    assert p2.history[0]["a1"] == 0.97
    np.testing.assert_array_equal(reg.reference("SB-1")["depth_m"], ref["depth_m"])
    assert json.loads((p2.path / "acceptance.json").read_text()) == rej


def test_listing_lookup_and_bad_names(tmp_path):
    reg = SensorRegistry(tmp_path / "reg")
    assert reg.profiles() == []
    for serial in ("SB-B", "SB-A"):
        reg.register(serial, accepted=False, run_dir=tmp_path, intrinsics=INTR, camera_in_tcp=None,
                     simulated=True, acceptance={"accepted": False})
    assert [p.serial for p in reg.profiles()] == ["SB-A", "SB-B"]
    stray = tmp_path / "reg" / "copy of SB-A\n"  # no sensor serial: not listed (its newline broke the table)
    stray.mkdir()
    (stray / "profile.json").write_text((tmp_path / "reg" / "SB-A" / "profile.json").read_text())
    assert [p.serial for p in reg.profiles()] == ["SB-A", "SB-B"]
    with pytest.raises(InputError, match="not in the registry"):
        reg.get("SB-C")
    with pytest.raises(InputError, match="valid registry name"):
        reg.get("../etc")
    with pytest.raises(InputError, match="no accepted reference"):
        reg.reference("SB-A")
    (tmp_path / "file").write_text("x")
    with pytest.raises(InputError, match="not a directory"):
        SensorRegistry(tmp_path / "file")


def test_location_from_environment(tmp_path, monkeypatch):
    monkeypatch.setenv("BUBBLE_REGISTRY", str(tmp_path / "envreg"))
    assert default_registry_dir() == tmp_path / "envreg"
    assert SensorRegistry().root == tmp_path / "envreg"
    monkeypatch.delenv("BUBBLE_REGISTRY")
    assert default_registry_dir().name == "sensors" and "bubble-bench" in str(default_registry_dir())
