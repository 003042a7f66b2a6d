"""Ctrl-C (SIGTERM, SIGHUP) in a command that trains, ``bubble train`` and ``python -m trainer.pretrain
train``: while the data loads it ends the command at once, as before any command (``KeyboardInterrupt``
or ``Terminated``, which the command line turns into its one line ``interrupted``); once training has
begun it ends the step in progress, which ``train_model`` checkpoints for ``--resume``
(``TrainConfig(write_on_stop=False, checkpoint_on_stop=True)``), and the command says where."""

from __future__ import annotations

import signal
import sys
import threading
from pathlib import Path

from collect.stop_signals import INTERRUPTS, exit_code, raise_interrupt, stop_signals_handled


class TrainingStop:
    """The stop of one training command::

        stop = TrainingStop()
        with stop.handled():
            result = train_model(config, progress_callback, stop.event)  # the callback calls stop.begin()
        if result.stopped:
            return stop.interrupted(result, config.out, "bubble")
        if stop.requested:  # after the last step, while the model was validated and written
            return stop.after_last_step(config.out, "bubble")
    """

    def __init__(self) -> None:
        self.event = threading.Event()  # train_model's stop_event
        self.signum: int | None = None  # the signal that set it
        self._begun = False

    def begin(self) -> None:
        """Training has begun (its first progress report): from now on a signal ends the step in
        progress, not the command."""
        self._begun = True

    @property
    def requested(self) -> bool:
        """Whether a signal asked training to stop."""
        return self.signum is not None

    def handled(self, *, process_ends: bool = False):
        """The with-block of ``INTERRUPTS`` around the training (``stop_signals_handled``;
        ``process_ends``: it is the command's outermost block)."""
        return stop_signals_handled(self._on_signal, INTERRUPTS, process_ends=process_ends)

    def _on_signal(self, signum: int) -> None:
        if not self._begun:
            raise_interrupt(signum)
        self.signum = signum
        self.event.set()

    def interrupted(self, result, model_dir: str | Path, tool: str) -> int:
        """Print the one line of a training ``result`` the stop ended, ``<tool>: interrupted: ...`` with
        where its checkpoint in ``model_dir`` is and how to resume; return the exit code (130 for
        Ctrl-C, 143 SIGTERM, 129 SIGHUP)."""
        from trainer.checkpoint import has_checkpoint

        kept = (f"its checkpoint at step {result.steps} ({result.train_s / 60:.1f} min of training) is in {model_dir}: "
                "continue with the same command and --resume" if has_checkpoint(model_dir) else "nothing to resume yet")
        print(f"{tool}: interrupted: {kept}", file=sys.stderr)
        return exit_code(self.signum if self.signum is not None else signal.SIGINT)

    def after_last_step(self, model_dir: str | Path, tool: str) -> int:
        """Print the one line of a stop that came after the training's last step, while the model was
        validated and written (the model in ``model_dir`` is whole); return the exit code."""
        print(f"{tool}: interrupted after the training's last step: the model in {model_dir} is complete",
              file=sys.stderr)
        return exit_code(self.signum)
