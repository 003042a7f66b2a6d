"""Train / validation splits of a ``FrameSet`` (the paper's protocols).

* ``frames``: in-class, a seeded random 70/30 split of the frames of each object (the paper's).
* ``poses``: in-class by contact pose, a seeded random 70/30 split of the contact poses of each
  object (frames of one press never straddle the split: held-out poses).
* ``holdout_object``: leave one object out (train on the others, validate on it).
* by session / sensor: validate on other session files (``--val-data``), no split function needed.

Free frames (no contact, pose -1) are split at random by frame in ``frames`` and ``poses``;
with a held-out object the other objects' free frames train and the held-out object's are left out.
Each (session, object) draws from its own generator, seeded by ``seed``, the session's index and
the object's name, and its free frames from another: which poses are held out depends on those and
on the object's pose ids only, not on how many frames the recording holds (was: one generator for
all, so a re-recording of the same plan with a few frames more or less held out other poses).
"""

from __future__ import annotations

import zlib

import numpy as np

from collect.errors import InputError
from trainer.dataset import FrameSet

SPLITS = ("frames", "poses")
TRAIN_FRACTION = 0.7


def _split_groups(groups: np.ndarray, rng, fraction: float) -> np.ndarray:
    """Boolean train mask over items of ``groups`` (n,) so that ~``fraction`` of the groups train."""
    unique = np.unique(groups)
    perm = rng.permutation(len(unique))
    n_train = int(round(fraction * len(unique)))
    if len(unique) >= 2:
        n_train = min(max(n_train, 1), len(unique) - 1)
    return np.isin(groups, unique[perm[:n_train]])


def split_in_class(frames: FrameSet, by: str = "poses", seed: int = 0, fraction: float = TRAIN_FRACTION):
    """``(train_idx, val_idx)`` int64 arrays: within each (session, object), 70/30 of frames or poses."""
    if by not in SPLITS:
        raise InputError(f"unknown split {by!r}; choose one of {', '.join(SPLITS)}")
    train = np.zeros(len(frames), dtype=bool)
    keys = {(int(s), str(o)) for s, o in zip(frames.session, frames.object_name)}
    for s, o in sorted(keys):
        members = np.flatnonzero((frames.session == s) & (frames.object_name == o))
        key = (int(seed), s, zlib.crc32(o.encode()))
        if by == "frames":
            mask = _split_groups(np.arange(len(members)), np.random.default_rng(key), fraction)
        else:
            contact = frames.pose_id[members] >= 0
            mask = np.zeros(len(members), dtype=bool)
            if contact.any():
                mask[contact] = _split_groups(frames.pose_id[members][contact], np.random.default_rng(key), fraction)
            if (~contact).any():
                mask[~contact] = _split_groups(np.arange(int((~contact).sum())), np.random.default_rng((*key, 1)),
                                               fraction)
        train[members] = mask
    return np.flatnonzero(train), np.flatnonzero(~train)


def split_holdout_object(frames: FrameSet, name: str):
    """``(train_idx, val_idx)``: the contact frames of object ``name`` validate, the frames of every
    other object train; no frame recorded for ``name`` trains, its no-contact frames included (was:
    those trained, and the model's metadata listed ``name`` among its training objects)."""
    if name not in set(frames.object_name):
        raise InputError(f"held-out object {name!r} is not in the data ({', '.join(sorted(set(frames.object_name) - {''}))})")
    of_held = frames.object_name == name
    held = of_held & (frames.pose_id >= 0)
    train = ~of_held
    if not held.any():
        raise InputError(f"object {name!r} has no contact frames to hold out")
    if not train.any():
        raise InputError(f"holding out {name!r} leaves no other object to train on")
    return np.flatnonzero(train), np.flatnonzero(held)
