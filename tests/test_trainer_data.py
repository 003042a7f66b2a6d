"""Frame loading, splits, input geometry and IR normalization."""

import numpy as np
import pytest
import torch

from collect.errors import InputError
from trainer.augmentation import augment_ir
from trainer.dataset import load_frames, to_network_tensors
from trainer.losses import contact_weights, masked_l1
from trainer.preprocessing import InputGeometry, IRNormalization
from trainer.splits import split_holdout_object, split_in_class


def test_load_frames_contact_plus_some_free(synthetic_session):
    frames = load_frames([synthetic_session], free_fraction=0.25)
    contact = np.isin(frames.phase, ["press", "hold"])
    assert contact.sum() == 2 * 2 * 2 * 3  # objects x poses x phases x frames
    assert (frames.phase == "free").sum() == 6  # 0.25 x 24 contact frames (of the 8 free ones)
    assert set(frames.object_name) == {"mug", "box"} and frames.true_depth is not None
    assert frames.sources[0].sensor_serial == "SYN-0001" and len(frames.sources[0].sha256) == 64
    with pytest.raises(InputError, match="unknown object"):
        load_frames([synthetic_session], objects=["teapot"])


def test_pose_split_never_straddles_a_pose_and_is_seeded(make_synthetic_session, tmp_path):
    frames = load_frames([make_synthetic_session(tmp_path / "s.h5", poses_per_object=5)])
    train, val = split_in_class(frames, by="poses", seed=3)
    assert len(np.intersect1d(train, val)) == 0 and len(train) + len(val) == len(frames)
    contact = frames.pose_id >= 0
    assert not set(frames.pose_id[train][contact[train]]) & set(frames.pose_id[val][contact[val]])
    for name in ("mug", "box"):  # 70/30 of the 5 poses of each object: 4 (round 3.5) train
        assert len(set(frames.pose_id[train][(frames.object_name[train] == name) & contact[train]])) == 4
    assert np.array_equal(split_in_class(frames, by="poses", seed=3)[0], train)
    f_train, f_val = split_in_class(frames, by="frames", seed=3)
    assert abs(len(f_train) / len(frames) - 0.7) < 0.05


def test_held_out_poses_do_not_depend_on_how_many_frames_were_recorded(make_synthetic_session, tmp_path):
    """A re-recording of the same plan holds a few frames more or fewer: the held-out poses stay the
    same (was: one generator for every object, whose draws for the first object's free frames moved
    the next object's pose choice)."""
    frames = load_frames([make_synthetic_session(tmp_path / "s.h5", poses_per_object=5)], free_fraction=0.25)
    fewer = frames.subset(np.flatnonzero(~((frames.object_name == "box") & (frames.phase == "free")))[1:])

    def held_out(fs):
        _, val = split_in_class(fs, by="poses", seed=3)
        return {(o, int(p)) for o, p in zip(fs.object_name[val], fs.pose_id[val]) if p >= 0}

    assert len(fewer) < len(frames) and held_out(fewer) == held_out(frames)


def test_sessions_of_one_pose_plan_hold_out_the_same_poses_whatever_their_order(make_synthetic_session, tmp_path):
    """Two recordings of one plan (two sensors, the same ``bubble collect --seed``) press the same poses
    under the same ids: a pose held out of one trains in neither (was: each session drew its own, and
    every held-out contact frame had its pose trained in the other session)."""
    a = make_synthetic_session(tmp_path / "a.h5", poses_per_object=5, seed=1, sensor_serial="SYN-A")
    b = make_synthetic_session(tmp_path / "b.h5", poses_per_object=5, seed=2, sensor_serial="SYN-B")

    def split(paths):
        frames = load_frames(paths)
        train, val = split_in_class(frames, by="poses", seed=3)
        path = np.array([frames.sources[s].path for s in frames.session], dtype=object)
        poses = [{(p, o, int(i)) for p, o, i in zip(path[idx], frames.object_name[idx], frames.pose_id[idx]) if i >= 0}
                 for idx in (train, val)]
        return poses, {(o, i) for _, o, i in poses[0]}, {(o, i) for _, o, i in poses[1]}

    (trained, held_out), trained_poses, held_out_poses = split([a, b])
    assert held_out_poses and not trained_poses & held_out_poses
    assert {(p, o, i) for p, o, i in held_out if p == str(a)} == {(str(a), o, i) for o, i in held_out_poses}
    assert split([b, a])[0] == [trained, held_out]  # the order of --data changes nothing


def test_holdout_object_split(synthetic_session):
    frames = load_frames([synthetic_session])
    train, val = split_holdout_object(frames, "box")
    assert set(frames.object_name[val]) == {"box"} and (frames.pose_id[val] >= 0).all()
    assert "box" not in set(frames.object_name[train])  # its no-contact frames neither (they trained before)
    with pytest.raises(InputError):
        split_holdout_object(frames, "teapot")


def test_geometry_pads_native_frames_and_crops_back():
    g = InputGeometry(172, 224, 224, 224)
    assert g.scale == 1.0 and g.offset == (26, 0)
    frames = np.arange(2 * 172 * 224, dtype=np.float32).reshape(2, 172, 224)
    x = g.to_input(frames)
    assert x.shape == (2, 224, 224) and (x[:, :26] == 0).all() and (x[:, 198:] == 0).all()
    assert np.array_equal(g.to_native(x), frames)
    small = InputGeometry(172, 224, 64, 64)  # scale to fit, then pad
    assert small.content_size == (49, 64) and small.offset == (7, 0)
    assert small.to_native(small.to_input(np.ones((1, 172, 224), np.float32))).shape == (1, 172, 224)
    with pytest.raises(InputError, match="frame size"):
        g.to_input(np.zeros((1, 100, 100)))


def test_normalization_turns_gain_into_offset_and_tensors_mask_padding(synthetic_session):
    frames = load_frames([synthetic_session])
    norm = IRNormalization.fit(frames.ir)
    x = norm.apply(frames.ir[:1])
    assert abs(float(norm.apply(frames.ir).mean())) < 0.05
    doubled = norm.apply(np.minimum(frames.ir[:1].astype(np.int64) * 2, 65535).astype(np.uint16))
    bright = frames.ir[:1] > 300
    assert np.allclose((doubled - x)[bright], np.log(2) / norm.std, atol=0.01)
    g = InputGeometry(172, 224, 224, 224)
    t = to_network_tensors(frames, g, norm)
    assert t.x.shape == (len(frames), 1, 224, 224) and t.content.shape == (1, 1, 224, 224)
    assert (t.depth[:, :, :26] == 0).all() and int(t.content.sum()) == 172 * 224
    aug = augment_ir(t.x[:2], t.content, norm.std, torch.Generator().manual_seed(0))
    assert (aug[:, :, :26] == 0).all() and not torch.equal(aug, t.x[:2])
    # without pixel noise (fine-tuning) each image is an affine map of itself: gain and contrast only
    inside = t.content[0, 0].bool()
    for src, out in zip(t.x[:2, 0], aug[:, 0]):
        slope, offset = np.polyfit(src[inside].numpy(), out[inside].numpy(), 1)
        assert np.allclose(out[inside].numpy(), slope * src[inside].numpy() + offset, atol=1e-4)
    noisy = augment_ir(t.x[:2], t.content, norm.std, torch.Generator().manual_seed(0), noise_std=0.03)
    assert 0.02 < float((noisy - aug)[:, :, inside].std()) < 0.04 and (noisy[:, :, :26] == 0).all()


def test_masked_l1_ignores_invalid_pixels():
    pred = torch.tensor([[[[0.1, 0.2]]]], requires_grad=True)
    target = torch.tensor([[[[0.12, 0.0]]]])
    valid = target > 0
    assert float(masked_l1(pred, target, valid).detach()) == pytest.approx(0.02)
    assert float(masked_l1(pred, target, valid, inverse=True).detach()) == pytest.approx(10 - 1 / 0.12)
    masked_l1(pred, target, torch.zeros_like(valid)).backward()  # no valid pixel: zero, still differentiable
    assert pred.grad is not None and float(pred.grad.abs().sum()) == 0.0


def test_contact_patches_follow_the_dents_and_weight_the_loss(synthetic_session):
    frames = load_frames([synthetic_session], free_fraction=0.25)
    assert frames.reference.shape == (2,) + frames.size  # one no-contact reference per object
    assert set(frames.reference_index[frames.object_name == "mug"]) != set(frames.reference_index[frames.object_name == "box"])
    contact = frames.contact()
    pressed = np.isin(frames.phase, ["press", "hold"])
    assert contact[frames.phase == "free"].sum() == 0  # the membrane at rest is its own reference
    assert (contact[pressed].sum(axis=(1, 2)) > 20).all()  # every 2-6 mm dent is found
    for frame, patch, ref in zip(frames.depth[pressed], contact[pressed], frames.reference[frames.reference_index[pressed]]):
        assert (ref - frame)[patch].min() > 0.5e-3  # pushed in towards the camera by more than 0.5 mm
    t = to_network_tensors(frames, InputGeometry(172, 224, 224, 224), IRNormalization.fit(frames.ir))
    assert int(t.contact.sum()) == int(contact.sum()) and not t.contact[:, :, :26].any()
    # ToF noise past the threshold at single pixels away from the dent is no contact: not weighted up
    k = np.flatnonzero(pressed)[0]
    specks = (np.array([30, 150, 80]), np.array([60, 180, 20]))  # pixels, and a 2x2 block at (80, 20)
    assert not contact[k][specks].any() and frames.depth[k][specks].all()
    frames.depth[k][specks] -= 2e-3
    frames.depth[k, 80:82, 20:22] -= 2e-3
    noisy = frames.contact()[k]
    assert not noisy[specks].any() and not noisy[80:82, 20:22].any()
    np.testing.assert_array_equal(noisy, contact[k])  # the dent itself is kept whole

    pred = torch.zeros(1, 1, 1, 2)
    target = torch.tensor([[[[0.1, 0.2]]]])
    weight = contact_weights(torch.tensor([[[[False, True]]]]), 9.0)  # the second pixel counts 10x
    assert float(masked_l1(pred, target, target > 0, weight=weight)) == pytest.approx((0.1 + 10 * 0.2) / 11)


def test_the_ir_normalization_samples_every_column():
    """Was every k-th pixel, k = pixels // max_samples: where k was the frame's width, all in one column
    (here: mean 2.40 against 6.34)."""
    ir = np.full((100, 4, 8), 1000, np.uint16)
    ir[:, :, 0] = 10  # the housing's dark edge
    norm = IRNormalization.fit(ir, max_samples=400)  # 3200 pixels: k = 8, the width
    whole = np.log1p(ir.astype(np.float64))
    assert norm.mean == pytest.approx(whole.mean(), abs=0.2) and norm.std == pytest.approx(whole.std(), rel=0.15)
    assert IRNormalization.fit(ir, max_samples=400) == norm  # seeded


def test_frames_for_training_leave_the_true_depth(synthetic_session):
    """The training never reads it (was: loaded and copied by every split, 40 % of the frames' memory)."""
    assert load_frames([synthetic_session]).true_depth is not None
    assert load_frames([synthetic_session], with_truth=False).true_depth is None


def test_the_free_frames_of_a_session_do_not_depend_on_the_sessions_before_it(tmp_path, make_synthetic_session):
    """Was: one generator drew every session's free frames, so a session's share changed with the list."""
    a = make_synthetic_session(tmp_path / "a.h5", seed=1, n_reference=12)
    b = make_synthetic_session(tmp_path / "b.h5", seed=2, n_reference=12)

    def free_of_b(paths):
        frames = load_frames(paths, free_fraction=0.25)
        of_b = (frames.session == len(paths) - 1) & (frames.phase == "free")
        return frames.ir[of_b]

    alone, after_a = free_of_b([b]), free_of_b([a, b])
    assert len(alone) > 0 and np.array_equal(alone, after_a)
