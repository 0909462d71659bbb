"""Training callbacks: what a run does around the :class:`~jsgs.train.trainer.Trainer`'s steps without being
part of the optimisation (nerfstudio's training callbacks).

A callback subclasses :class:`Callback` and overrides the events it needs; the trainer calls them in list
order:

- ``on_setup(trainer)``: after :meth:`Trainer.setup` (settings checked, scene and Gaussians ready, resumed);
- ``on_step_begin(trainer, step)``: before step ``step`` (0-based);
- ``on_step_end(trainer, result)``: after it (:class:`StepResult`);
- ``on_eval(trainer, entry)``: after an evaluation (an entry of metrics.json ``evals``);
- ``on_checkpoint(trainer, step)``: at a checkpoint point after ``step`` steps (evaluation steps, the end,
  ``checkpoint_every``), after the evaluation of that step;
- ``on_end(trainer, doc)``: when the run ends, with the final metrics document (``status`` complete,
  stopped, diverged or failed), or None when an unexpected error stopped it.

The standard ones: :class:`ProgressBar`, :class:`StepProfiler`, :class:`CheckpointSaver`,
:class:`MetricsWriter` (:func:`jsgs.train.trainer.train` installs them in that order).

``trainer`` is the :class:`~jsgs.train.trainer.Trainer`; what the standard callbacks read of it is
:class:`TrainerProtocol`, so this module does not import the trainer, which imports it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

from jsgs.base.io import write_json_checked

if TYPE_CHECKING:
    import torch

    from jsgs.base.run_files import RunPaths
    from jsgs.train.config import TrainConfig
    from jsgs.train.profiler import Profiler


@dataclass
class StepResult:
    """What one training step logged: ``step`` (0-based), the view's name, the total loss, the terms and
    statistics (host floats, read after the backward), and the terms and statistics the step did not compute
    (``HookOutput.skipped``: their values are placeholders)."""

    step: int
    view: str
    loss: float
    terms: dict[str, float]
    stats: dict[str, float]
    skipped: frozenset[str] = frozenset()


class TrainerProtocol(Protocol):
    """What the standard callbacks read of the :class:`~jsgs.train.trainer.Trainer` that calls them."""

    cfg: TrainConfig | None
    paths: RunPaths
    start_step: int
    end_step: int
    splats: torch.nn.ParameterDict
    profiler: Profiler
    say: Callable[[str], None]

    def training_seconds(self) -> float: ...

    def num_gaussians(self) -> int: ...

    def save_checkpoint(self, step_done: int) -> str: ...

    def status_at(self, step_done: int) -> str: ...

    def metrics_doc(self, status: str, step: int, error: str | None = None) -> dict[str, Any]: ...


class Callback:
    """Base class: every event is a no-op."""

    def on_setup(self, trainer: TrainerProtocol) -> None:
        pass

    def on_step_begin(self, trainer: TrainerProtocol, step: int) -> None:
        pass

    def on_step_end(self, trainer: TrainerProtocol, result: StepResult) -> None:
        pass

    def on_eval(self, trainer: TrainerProtocol, entry: dict[str, Any]) -> None:
        pass

    def on_checkpoint(self, trainer: TrainerProtocol, step: int) -> None:
        pass

    def on_end(self, trainer: TrainerProtocol, doc: dict[str, Any] | None) -> None:
        pass


def eval_line(e: dict[str, Any]) -> str:
    """One line of an evaluation entry (PSNR, SSIM, LPIPS, Gaussians, FPS, training time)."""

    def f(x: Any, fmt: str) -> str:
        return "n/a" if x is None else format(x, fmt)

    return (
        f"eval @ {e['step']}: PSNR {f(e['psnr'], '.3f')} SSIM {f(e['ssim'], '.4f')} "
        f"LPIPS {f(e['lpips'], '.4f')} "
        f"| {e['num_gaussians']} Gaussians | {f(e['fps'], '.1f')} FPS | train {e['train_time_s']:.1f} s"
    )


def duration(seconds: float) -> str:
    """``seconds`` as ``h:mm:ss`` (``1:02:03``), or ``m:ss`` under an hour (``2:05``)."""
    s = max(0, round(seconds))
    h, rest = divmod(s, 3600)
    m, sec = divmod(rest, 60)
    return f"{h}:{m:02d}:{sec:02d}" if h else f"{m}:{sec:02d}"


class ProgressBar(Callback):
    """Progress: on a terminal a tqdm bar with the loss, the number of Gaussians and the terms (every
    ``log_every`` steps); elsewhere (a log file, a pipe) one plain line every twentieth of the run, so logs
    hold no carriage-return redraws. Both give the time per step over the last interval and the projected
    training time to the end at that pace (``ETA``), on the trainer's training clock (evaluations and
    checkpoints do not count): a MCMC model grows and its steps get slower, so the recent pace projects
    better than the mean since the start. After the run's first :attr:`ESTIMATE_AFTER` steps, one line
    estimates the whole training time at that pace (a lower bound when the model grows). A term or statistic
    the step did not compute (:attr:`StepResult.skipped`) shows its latest computed value and that step
    (1-based, as the line counts): ``fro=0.0051@29``; none before one was computed. Evaluation lines go to the
    bar or the trainer's log; ``enabled`` false: only those."""

    #: the steps after which the start estimate is printed
    ESTIMATE_AFTER = 10

    def __init__(self, enabled: bool = True, terminal: bool | None = None) -> None:
        import sys

        self.enabled = enabled
        self.terminal = sys.stderr.isatty() if terminal is None else terminal
        self.bar: Any = None
        self._mark: tuple[float, int] = (0.0, 0)  # (training seconds, steps done) at the last report
        self._start: tuple[float, int] = (0.0, 0)  # (training seconds, steps done) when this process began
        # the latest step of each set of skipped names (a hook's are few: JSGS's controller, none): where a
        # skipped value's latest computed one is, at one dict write per step
        self._latest: dict[frozenset[str], StepResult] = {}

    def _pace(self, trainer: TrainerProtocol, done: int) -> str:
        """``12.3 ms/step, ETA 5:07`` over the steps since the last report; moves the mark."""
        now = trainer.training_seconds()
        t_mark, s_mark = self._mark
        self._mark = (now, done)
        if done <= s_mark or now <= t_mark:
            return ""
        per_step = (now - t_mark) / (done - s_mark)
        left = max(trainer.end_step - done, 0)
        return f"{1000 * per_step:.1f} ms/step, ETA {duration(per_step * left)}"

    def on_setup(self, trainer: TrainerProtocol) -> None:
        cfg = trainer.cfg
        assert cfg is not None
        if not (self.enabled and trainer.start_step < cfg.iterations):
            return
        if self.terminal:
            from tqdm import tqdm

            self.bar = tqdm(
                total=cfg.iterations, initial=trainer.start_step, dynamic_ncols=True, unit="it", desc="train"
            )
        self._mark = (trainer.training_seconds(), trainer.start_step)
        self._start = self._mark

    def _estimate(self, trainer: TrainerProtocol, done: int) -> str | None:
        """The start estimate line once ``ESTIMATE_AFTER`` steps of this process are done (None otherwise)."""
        t0, s0 = self._start
        if done - s0 != self.ESTIMATE_AFTER or done >= trainer.end_step:
            return None
        per_step = (trainer.training_seconds() - t0) / (done - s0)
        left = trainer.end_step - done
        return (
            f"train: estimate after {done - s0} steps: {1000 * per_step:.1f} ms/step, about "
            f"{duration(per_step * left)} for the remaining {left} steps (more if the model grows), "
            "plus evaluations"
        )

    def _held(self, name: str) -> str:
        """``=value@step`` of the latest step that computed ``name`` ("" where none did)."""
        steps = [r for skipped, r in self._latest.items() if name not in skipped]
        if not steps:
            return ""
        r = max(steps, key=lambda r: r.step)
        value = r.terms[name] if name in r.terms else r.stats.get(name)
        return "" if value is None else f"={value:.4g}@{r.step + 1}"

    def _summary(self, trainer: TrainerProtocol, result: StepResult) -> str:
        parts = [f"loss={result.loss:.4f}", f"#G={trainer.num_gaussians()}"]
        for part in (result.terms, result.stats):
            for k, v in part.items():
                if k == "photometric" and part is result.terms:
                    continue
                if k not in result.skipped:
                    parts.append(f"{k}={v:.4g}")
                elif held := self._held(k):
                    parts.append(k + held)
        return " ".join(parts)

    def on_step_end(self, trainer: TrainerProtocol, result: StepResult) -> None:
        cfg = trainer.cfg
        assert cfg is not None
        if not self.enabled:
            return
        done = result.step + 1
        self._latest[result.skipped] = result
        estimate = self._estimate(trainer, done)
        if estimate is not None:
            if self.bar is not None:
                self.bar.write(estimate)
            else:
                trainer.say(estimate)
        if self.bar is not None:
            self.bar.update(1)
            if done % cfg.log_every == 0 or done == trainer.end_step:
                pace = self._pace(trainer, done)
                summary = self._summary(trainer, result)
                self.bar.set_postfix_str(f"{pace} {summary}" if pace else summary, refresh=False)
            return
        every = max(cfg.log_every, cfg.iterations // 20)
        if done % every == 0 or done == trainer.end_step:
            pace = self._pace(trainer, done)
            trainer.say(
                f"train: step {done}/{cfg.iterations} ({100 * done // cfg.iterations}%), "
                + (f"{pace}, " if pace else "")
                + self._summary(trainer, result)
            )

    def on_eval(self, trainer: TrainerProtocol, entry: dict[str, Any]) -> None:
        if self.bar is not None:
            self.bar.write(eval_line(entry))
        else:
            trainer.say(eval_line(entry))

    def on_end(self, trainer: TrainerProtocol, doc: dict[str, Any] | None) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None


class StepProfiler(Callback):
    """Per-phase device-synchronised times of every step (``profile_ms_per_step`` in metrics.json; slows a
    GPU run). Turns the trainer's :class:`~jsgs.train.profiler.Profiler` on and counts the steps it timed."""

    def __init__(self, enabled: bool = True) -> None:
        self.enabled = enabled

    def on_setup(self, trainer: TrainerProtocol) -> None:
        trainer.profiler.enabled = self.enabled

    def on_step_end(self, trainer: TrainerProtocol, result: StepResult) -> None:
        trainer.profiler.steps += 1


class CheckpointSaver(Callback):
    """Writes ``checkpoints/step_XXXXXX.pt`` at every checkpoint point (:meth:`Trainer.save_checkpoint`)."""

    def on_checkpoint(self, trainer: TrainerProtocol, step: int) -> None:
        trainer.save_checkpoint(step)


class MetricsWriter(Callback):
    """Writes ``metrics.json`` (validated against its schema) at every checkpoint point and at the end."""

    def _write(self, trainer: TrainerProtocol, doc: dict[str, Any]) -> None:
        write_json_checked(trainer.paths.metrics, doc, "metrics")

    def on_checkpoint(self, trainer: TrainerProtocol, step: int) -> None:
        self._write(trainer, trainer.metrics_doc(trainer.status_at(step), step))

    def on_end(self, trainer: TrainerProtocol, doc: dict[str, Any] | None) -> None:
        if doc is not None:
            self._write(trainer, doc)
