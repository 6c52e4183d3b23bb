"""Where and how Lightning runs: the ``trainer`` config group (:class:`TrainerSettings`), the
precision it resolves to, device checks, seeding and the ``lightning.Trainer`` it builds.

Lightning and torch are imported inside the functions that use them: a stage that only checks a
device (:func:`check_device`) imports torch, not Lightning, and reading the settings
(:meth:`TrainerSettings.from_cfg`, as ``check_params`` does) imports neither on a CPU machine."""

from __future__ import annotations

import logging
import os
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path
from typing import Any

from traffictwin.config import ConfigError, spec, typed
from traffictwin.threads import pin_threads

PRECISIONS = (
    "auto",  # resolved by resolve_precision: bf16-mixed where the hardware has native bf16, else 32-true
    "32-true",
    "32",
    "64-true",
    "16-mixed",
    "bf16-mixed",
    "bf16-true",
    "16-true",
    "transformer-engine",
)
ACCELERATORS = ("cpu", "gpu", "cuda", "mps", "tpu", "auto")


@dataclass(frozen=True)
class TrainerSettings:
    """Where and how Lightning runs: one CPU, one GPU, or DDP over ``devices`` x ``num_nodes``.

    Also the schema of the ``trainer`` config group (:meth:`from_cfg`); ``deterministic`` and
    ``num_threads`` may be left out there, every other key is required.
    """

    accelerator: str = spec("cpu", choices=ACCELERATORS)
    devices: int | str = 1  # >= 1, -1 (all) or a Lightning string ("auto", "0,1")
    num_nodes: int = spec(1, min=1)
    strategy: str = "auto"
    precision: str | int = spec("32-true", choices=[*PRECISIONS, 32, 64])
    num_workers: int = spec(0, min=0)
    deterministic: bool | str | None = (
        None  # None: True on CPU, "warn" elsewhere (CUDA upsampling backward)
    )
    num_threads: int = spec(0, min=0)  # torch intra-op CPU threads; 0 = torch's default

    OPTIONAL = ("deterministic", "num_threads")

    @classmethod
    def from_cfg(cls, cfg: Any, *, source: str | Path, key: str = "trainer") -> TrainerSettings:
        """Validate the ``trainer`` group of ``cfg`` (the whole params tree) once; errors name ``source``."""
        node = cfg.get(key) if isinstance(cfg, Mapping) or hasattr(cfg, "get") else None
        if node is None:
            raise ConfigError(f"{source}: '{key}' is missing")
        for f in fields(cls):
            if f.name not in cls.OPTIONAL and f.name not in node:
                raise ConfigError(f"{source}: '{key}.{f.name}' is missing")
        settings = typed(node, cls, key=key, source=source)
        d = settings.devices
        if isinstance(d, int) and d < 1 and d != -1:
            raise ConfigError(f"{source}: '{key}.devices' must be >= 1 or -1, got {d!r}")
        return replace(
            settings, precision=resolve_precision(str(settings.precision), settings.accelerator)
        )

    def check_available(self, source: str | Path, key: str = "trainer") -> None:
        """The requested hardware must exist on this machine: CUDA for ``gpu``/``cuda``, at most
        as many GPUs (or, on CPU, cores) as ``devices`` asks for. Stages call this right after
        :meth:`from_cfg`, before any output is touched; ConfigError names the setting and what
        is available."""
        want = self.devices if isinstance(self.devices, int) and self.devices > 0 else None
        if self.accelerator in ("gpu", "cuda"):
            import torch

            if not torch.cuda.is_available():
                raise ConfigError(
                    f"{source}: '{key}.accelerator' is {self.accelerator!r} but this machine has no "
                    f"CUDA device (torch {torch.__version__}, torch.cuda.is_available() is False): "
                    f"use trainer=cpu"
                )
            have = torch.cuda.device_count()
            if want is not None and want > have:
                raise ConfigError(
                    f"{source}: '{key}.devices' is {want} but this machine has {have} CUDA device(s)"
                )
        elif self.accelerator == "cpu" and want is not None and want > (os.cpu_count() or 1):
            raise ConfigError(
                f"{source}: '{key}.devices' is {want} CPU processes but this machine has "
                f"{os.cpu_count()} cores"
            )
        self._check_lightning(source, key)

    def _check_lightning(self, source: str | Path, key: str) -> None:
        """Lightning must accept accelerator/devices/num_nodes/strategy/precision together on this
        machine (e.g. ``mps`` or ``tpu`` that is not there, a device list on CPU, an unknown
        strategy): a throw-away ``Trainer`` is built; its error becomes a ConfigError."""
        import lightning as L
        from lightning.fabric.utilities.exceptions import MisconfigurationException

        # Lightning's startup banners -> warnings only (as in build_trainer)
        logging.getLogger("lightning.pytorch.utilities.rank_zero").setLevel(logging.WARNING)
        try:
            L.Trainer(
                accelerator=self.accelerator,
                devices=self.devices,
                num_nodes=self.num_nodes,
                strategy=self.strategy,
                precision=self.precision,  # type: ignore[arg-type]
                logger=False,
                enable_checkpointing=False,
                enable_progress_bar=False,
                enable_model_summary=False,
            )
        except (MisconfigurationException, ValueError, TypeError, ImportError, RuntimeError) as exc:
            msg = " | ".join(ln.strip() for ln in str(exc).splitlines() if ln.strip())
            raise ConfigError(
                f"{source}: '{key}' (accelerator={self.accelerator!r}, devices={self.devices!r}, "
                f"num_nodes={self.num_nodes}, strategy={self.strategy!r}, "
                f"precision={self.precision!r}) cannot run here: {type(exc).__name__}: {msg}"
            ) from None

    def resolved_deterministic(self) -> bool | str:
        if self.deterministic is not None:
            return self.deterministic
        return True if self.accelerator == "cpu" else "warn"

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


def native_bf16_cpu(cpuinfo: str | Path = "/proc/cpuinfo") -> bool:
    """Whether this CPU computes bfloat16 natively (x86 ``avx512_bf16`` or ``amx_bf16``, as
    ``/proc/cpuinfo`` lists them). Elsewhere oneDNN emulates bf16, which is slower than fp32, so
    an unreadable ``cpuinfo`` (another OS) counts as no."""
    try:
        text = Path(cpuinfo).read_text(errors="replace")
    except OSError:
        return False
    flags = next((ln for ln in text.splitlines() if ln.startswith(("flags", "Features"))), "")
    have = set(flags.split(":", 1)[-1].split())
    return bool(have & {"avx512_bf16", "amx_bf16"})


def resolve_precision(
    precision: str, accelerator: str, cpuinfo: str | Path = "/proc/cpuinfo"
) -> str:
    """Lightning's precision for the ``trainer.precision`` setting: ``auto`` becomes ``bf16-mixed``
    where the hardware has native bf16 (a CUDA GPU that supports it; a CPU with AVX512-BF16 or
    AMX-BF16, :func:`native_bf16_cpu`) and ``32-true`` elsewhere; any other value is kept.
    Measured on the default fusion network's training step (2-core AMD EPYC with AVX512-BF16):
    0.258 s in fp32, 0.153 s in bf16 autocast at batch 8 (README, *How long it takes*)."""
    if precision != "auto":
        return precision
    if accelerator in ("gpu", "cuda", "auto"):
        import torch

        if torch.cuda.is_available():
            return "bf16-mixed" if torch.cuda.is_bf16_supported() else "32-true"
    if accelerator in ("cpu", "auto"):
        return "bf16-mixed" if native_bf16_cpu(cpuinfo) else "32-true"
    return "32-true"


def check_device(device: str, source: str | Path, key: str) -> None:
    """A torch device setting (``cpu``, ``cuda``, ``cuda:1``, ...) must name a device this machine
    has; ConfigError naming ``key`` otherwise (stages call it before any output is touched)."""
    import torch

    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError) as exc:
        raise ConfigError(
            f"{source}: '{key}' is not a torch device, got {device!r} ({exc})"
        ) from None
    if dev.type == "cuda":
        have = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if have <= (dev.index or 0):
            raise ConfigError(
                f"{source}: '{key}' is {device!r} but this machine has {have} CUDA device(s): use cpu"
            )
    elif dev.type != "cpu":
        raise ConfigError(f"{source}: '{key}' must be cpu or cuda[:i], got {device!r}")


def seed_everything(seed: int) -> None:
    """Seed python, numpy and torch (and dataloader workers, via Lightning) for run-to-run determinism."""
    import lightning as L

    os.environ.setdefault("PYTHONHASHSEED", "0")
    L.seed_everything(int(seed), workers=True, verbose=False)


def build_trainer(
    settings: TrainerSettings,
    *,
    max_epochs: int,
    callbacks: Sequence[Any] = (),
    default_root_dir: str | Path | None = None,
    enable_progress_bar: bool | None = None,
    **extra: Any,
) -> Any:
    """A ``lightning.Trainer`` for ``settings``; no Lightning logger (see :class:`History`).

    ``enable_progress_bar``: ``None`` shows Lightning's progress bar only when stderr is a
    terminal (not in DVC or CI logs, which get :class:`History`'s one line per epoch).
    ``extra``: further ``lightning.Trainer`` arguments (``fast_dev_run``, ``gradient_clip_val``,
    ``limit_val_batches``, ...); ``num_sanity_val_steps`` is 0 unless given.
    """
    import sys

    import lightning as L
    from lightning.pytorch.callbacks import ModelCheckpoint

    from traffictwin.trainer.callbacks import FiniteGuard

    if settings.num_threads > 0:
        pin_threads(settings.num_threads)
    # Lightning's startup banners ("GPU available", logger tips) -> warnings only; epochs are logged by History
    logging.getLogger("lightning.pytorch.utilities.rank_zero").setLevel(logging.WARNING)
    callbacks = list(callbacks)
    if not any(isinstance(cb, FiniteGuard) for cb in callbacks):
        callbacks.append(FiniteGuard())
    kw: dict[str, Any] = dict(
        accelerator=settings.accelerator,
        devices=settings.devices,
        num_nodes=settings.num_nodes,
        strategy=settings.strategy,
        precision=settings.precision,
        deterministic=settings.resolved_deterministic(),
        max_epochs=int(max_epochs),
        callbacks=list(callbacks),
        logger=False,
        # Lightning's implicit checkpoint callback would write into the cwd; only checkpoint when asked
        enable_checkpointing=any(isinstance(cb, ModelCheckpoint) for cb in callbacks),
        enable_progress_bar=sys.stderr.isatty()
        if enable_progress_bar is None
        else enable_progress_bar,
        enable_model_summary=False,
        num_sanity_val_steps=0,
        default_root_dir=str(default_root_dir) if default_root_dir else None,
    )
    kw.update(extra)
    return L.Trainer(**kw)
