"""The trainer's defaults, in a module without torch, so that the command line can offer and
show them without loading the trainer (``TrainConfig`` takes its defaults from here)."""

#: Network names, one module each under ``trainer.networks`` (``ARCHITECTURES`` builds them).
ARCH_NAMES = ("resnet", "packnet", "bts")
DEFAULT_ARCH = "resnet"
#: Default width multiplier per architecture: the widest whose deployed inference keeps >= 60 fps
#: batch 1 at 224 x 224 on a 2-core CPU for ``resnet`` (see docs/bench_trainer.md).
DEFAULT_WIDTHS = {"resnet": 0.375, "packnet": 0.25, "bts": 0.25}
#: Bubble depth range (m): the membrane lies 55-100 mm from the camera.
DEFAULT_MIN_DEPTH = 0.04
DEFAULT_MAX_DEPTH = 0.12
#: Budget when neither epochs nor minutes are given (the product's fine-tuning promise), minutes.
DEFAULT_MINUTES = 3.0
#: Extra L1 weight of the contact-patch pixels (``trainer.losses.contact_weights``).
DEFAULT_CONTACT_WEIGHT = 10.0
#: Adam's learning rate at the start (the paper's), halved during the run (``LR_HALVING_FRACTION``).
DEFAULT_LR = 2e-4
#: Largest learning rate accepted (5000 times the default; Adam's steps are about this large).
MAX_LR = 1.0
#: Largest contact weight accepted (100 times the default; a contact pixel then weighs 1001 free ones).
MAX_CONTACT_WEIGHT = 1000.0
#: Largest budgets accepted: 10000 epochs (a fine-tune takes about 6 in its 3 minutes) and a week
#: of training, minutes.
MAX_EPOCHS = 10000.0
MAX_MINUTES = 7 * 24 * 60.0
#: Largest seed accepted (torch and numpy take it as is).
MAX_SEED = 2**32 - 1
#: Frames per optimizer step (small: a CPU, and a few hundred frames per sensor).
DEFAULT_BATCH_SIZE = 8
