"""Train / validation splits of a ``FrameSet`` (the paper's protocols).

* ``frames``: in-class, a seeded random 70/30 split of the frames of each object (the paper's).
* ``poses``: in-class by contact pose, a seeded random 70/30 split of the contact poses of each
  object (frames of one press never straddle the split: held-out poses).
* ``holdout_object``: leave one object out (train on the others, validate on it).
* by session / sensor: validate on other session files (``--val-data``), no split function needed.

Free frames (no contact, pose -1) are split at random by frame in ``frames`` and ``poses``;
with a held-out object the other objects' free frames train and the held-out object's are left out.
The held-out poses of an object are drawn once for every session, from a generator seeded by
``seed`` and the object's name, over the pose ids any session pressed it in: sessions recorded from
one pose plan (``bubble collect --seed``, the same for every sensor) press the same poses under the
same ids, so a pose held out of one trains in none (was: each session drew its own, and a pose held
out of one session trained in another of the same plan). Which poses are held out depends on those
ids alone, not on how many frames the recording holds nor on the order of the sessions. The frames
of the ``frames`` split, and the free frames, are drawn per (session, object), seeded by ``seed``,
the session file's SHA-256 and the object's name.
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
    """``(train_idx, val_idx)`` int64 arrays: 70/30 of each object's contact poses, the same in every
    session (``poses``), or of the frames of each (session, object) (``frames``); free frames by frame."""
    if by not in SPLITS:
        raise InputError(f"unknown split {by!r}; choose one of {', '.join(SPLITS)}")
    train = np.zeros(len(frames), dtype=bool)
    by_frame = frames.pose_id < 0 if by == "poses" else np.ones(len(frames), dtype=bool)
    for o in sorted(set(frames.object_name)):
        of_object, name_key = frames.object_name == o, zlib.crc32(o.encode())
        by_pose = np.flatnonzero(of_object & ~by_frame)
        if len(by_pose):
            rng = np.random.default_rng((int(seed), name_key))
            train[by_pose] = _split_groups(frames.pose_id[by_pose], rng, fraction)
        for s, source in enumerate(frames.sources):
            members = np.flatnonzero(of_object & by_frame & (frames.session == s))
            if len(members):
                rng = np.random.default_rng((int(seed), int(source.sha256[:16], 16), name_key, 1))
                train[members] = _split_groups(np.arange(len(members)), rng, fraction)
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
