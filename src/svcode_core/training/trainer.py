"""Training on a simulated dataset: Adam, cosine annealing, checkpoints, logs.

The trainer is method-agnostic: a task (:mod:`.tasks`) builds the model and its samples
and names its ``(prediction, target)`` stages, so SV-CoDe (patches, two stages) and the
learned baselines (whole frames, one stage) share the loss, the schedule, the checkpoint
format and the logs. The task follows from the type of the model configuration.

A run folder holds

* ``checkpoints/``: ``epoch-NNNN.safetensors`` (weights, a :func:`save_model` file) and
  ``epoch-NNNN.pt`` (optimizer, scheduler, RNG state, history: plain tensors and numbers,
  read back with ``torch.load(weights_only=True)``), plus ``latest.json`` naming them.
  Each file is written to a temporary name and moved into place with :func:`os.replace`,
  and ``latest.json`` is replaced last, so an interruption at any moment leaves the
  previous complete checkpoint in charge;
* ``best.safetensors``: the model with the best validation reconstruction PSNR, with the
  system and the training metadata (:func:`~svcode_core.network.save_model`); when the
  best epoch is the latest checkpoint's, a resume writes it again from that checkpoint
  if it is missing (a resume state kept in a repository need not hold the weights twice);
* ``log.csv`` and ``log.json`` (per-epoch metrics; the JSON also has the configurations
  and every step's loss) and ``loss.png`` (the curves).

Training is reproducible: the model initialisation, each epoch's patch draw and every
noise draw follow from the seed and the epoch, so ``resume`` after an interruption
continues exactly as the uninterrupted run would (on the same device and thread count).
The training steps' forward pass runs under bf16 autocast on CUDA, and on any device with
``precision="bf16"``; the loss is always computed in float32, and validation runs in
float32, so that runs in either precision are scored alike. On a device with bf16 units,
an SV-CoDe model's best epoch is validated once more in bf16, as reconstructions run it
there, and the PSNR it loses is written into ``best.safetensors`` (``precision_check``):
reconstructions with ``precision="auto"`` run such a model in bf16 when the loss is at most
0.05 dB.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import math
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from safetensors.torch import load_file
from torch.nn.parallel import DistributedDataParallel
from tqdm.auto import tqdm

from ..io import atomic_path, write_text_atomic
from ..methods.base import native_bf16
from ..methods.learned import FourierNetConfig, MultiWienerConfig
from ..methods.model_file import load_model, save_model
from ..methods.svcode import bf16_network
from ..network import ModelConfig, SVCoDe, with_lens_context
from ..network.compiled import compile_model
from .dataset import TrainingData
from .distributed import DistInfo, all_reduce_sum, barrier
from .loss import field_weights, joint_loss, psnr_per_sample, seen_by_every_lens, ssim_per_sample
from .sampler import EpochSampler, derive_seed
from .settings import TrainConfig
from .tasks import Stages, training_task

__all__ = ["TrainConfig", "Trainer"]

CHECKPOINTS = "checkpoints"
LATEST = "latest.json"
BEST = "best.safetensors"


def _with_defaults(config: Any, stored: dict[str, Any]) -> dict[str, Any]:
    """A checkpoint's stored configuration over the defaults of ``config``'s fields.

    A field added after the checkpoint was written compares at its default, which is the
    behaviour the checkpoint was trained with (new fields default to the old behaviour).
    """
    defaults = {f.name: f.default for f in dataclasses.fields(config)
                if f.default is not dataclasses.MISSING}  # no stored config has factories
    return json.loads(json.dumps({**defaults, **stored}))


def _cxx_compiler() -> str | None:
    """The C++ compiler torch.compile will use on the CPU (torch's own search: ``CXX``,
    else ``g++``), or ``None``."""
    from torch._inductor import cpp_builder, exc

    try:
        return cpp_builder.get_cpp_compiler()
    except exc.InvalidCxxCompiler:
        return None


@dataclass(frozen=True)
class _WarmupCosine:
    """Learning-rate factor at step ``t``: linear warm-up, then cosine to ``floor``."""

    warmup: int
    total: int
    floor: float

    def __call__(self, step: int) -> float:
        if step < self.warmup:
            return (step + 1) / self.warmup
        span = max(self.total - self.warmup, 1)
        progress = min((step - self.warmup) / span, 1.0)
        return self.floor + (1 - self.floor) * 0.5 * (1 + math.cos(math.pi * progress))


#: what to do about a damaged checkpoint
_RESTART = ("restore the checkpoint files from a copy, or train again without --resume "
            "(into a new --out folder to keep this one)")

#: the keys of a checkpoint's state file
_STATE_KEYS = ("epoch", "global_step", "optimizer", "scheduler", "torch_rng", "cuda_rng",
               "history", "step_losses", "best", "model_config", "train_config")


def _read_checkpoint(path: Path, read: Callable[[Path], Any]) -> Any:
    """``read(path)`` of a checkpoint file; a damaged or truncated one is refused in one
    line that names it and says what to do (a missing one is a :class:`FileNotFoundError`)."""
    if not path.is_file():
        raise FileNotFoundError(f"{path} is missing: {_RESTART}")
    try:
        data = read(path)
    except Exception as err:  # zip, pickle, safetensors: each library raises its own
        reason = " ".join(str(err).split(". ")[0].split()) or type(err).__name__
        raise ValueError(f"{path} is damaged or truncated ({reason}): {_RESTART}") from None
    if path.suffix == ".pt" and not (isinstance(data, dict) and set(_STATE_KEYS) <= set(data)):
        raise ValueError(f"{path} is not a checkpoint state of this trainer: {_RESTART}")
    return data


def _atomic_write(path: Path, write: Callable[[Path], Any]) -> None:
    with atomic_path(path) as partial:
        write(partial)


class Trainer:
    """Train SV-CoDe or a learned baseline on a :class:`TrainingData` folder.

    Parameters
    ----------
    data : TrainingData
    out_dir : str or Path
        Run folder (created).
    model_config : ModelConfig, MultiWienerConfig or FourierNetConfig
        SV-CoDe (patch-wise), MultiWienerNet or SV-FourierNet (whole frames).
    config : TrainConfig
    device : str or torch.device
    dist : DistInfo, optional
        This process's place in a ``torchrun`` job; the model is wrapped in
        DistributedDataParallel when there are several processes.
    progress : bool
        Show a progress bar per epoch (rank 0 only).
    init_weights : str or Path, optional
        A model file to start from instead of a random initialisation (fine-tuning); its
        architecture and network configuration must be ``model_config``'s. A resumed run
        continues from its checkpoint instead. The file's measured tile overlap
        (``overlap_check``) is carried into every file the run writes, marked as inherited.

    Examples
    --------
    Three epochs of the ``mini`` network on a dataset written by ``svcode dataset``
    (see ``tests/test_training.py`` for a run on a tiny system)::

        trainer = Trainer(TrainingData("data"), "run", ModelConfig.mini(), TrainConfig(epochs=3))
        trainer.fit()
    """

    def __init__(
        self,
        data: TrainingData,
        out_dir: str | Path,
        model_config: ModelConfig | MultiWienerConfig | FourierNetConfig,
        config: TrainConfig,
        device: str | torch.device = "cpu",
        dist: DistInfo | None = None,
        progress: bool = True,
        init_weights: str | Path | None = None,
    ) -> None:
        self.data, self.system = data, data.system
        self.config = config.validate()
        #: where every lens sees the sub-view (for the partial weight; None when it is 1)
        self.seen_by_all = (seen_by_every_lens(self.system)
                            if self.config.partial_weight != 1.0 else None)
        self.model_config = model_config.validate()
        self.out = Path(out_dir)
        self.device = torch.device(device)
        self.dist = dist or DistInfo()
        self.progress = progress and self.dist.is_main
        self.autocast = config.precision == "bf16" or (
            config.precision == "auto" and self.device.type == "cuda")

        self.task = training_task(self.model_config)
        self.stages = self.task.stages
        sampling: dict[str, Any] = {"normalise_exposure": config.normalise_exposure}
        if config.patch_size is not None:
            if self.task.unit != "patches":
                raise ValueError(f"patch_size: {self.task.label} trains on whole frames")
            sampling["patch"] = config.patch_size
        torch.manual_seed(derive_seed(config.seed, 4))
        self.model = self.task.build(self.system)
        #: metadata carried from the initial weights' file into every file written
        self.inherited: dict[str, Any] = {}
        if init_weights is not None:
            self._load_initial_weights(Path(init_weights))
        self.model.to(self.device)
        self.net: torch.nn.Module = self.model
        if self.dist.active:
            ids = [self.device.index] if self.device.type == "cuda" else None
            self.net = DistributedDataParallel(self.model, device_ids=ids)
        if config.compile and self.device.type == "cpu" and not _cxx_compiler():
            raise RuntimeError("compile: torch.compile needs a C++ compiler on the CPU (g++, "
                               "or the one named by CXX); install one or train without "
                               "compiling")
        # one shape per step (drop_last), so one graph; validation stays uncompiled
        bf16_on_cpu = self.autocast and self.device.type == "cpu"
        if bf16_on_cpu and config.compile:
            warnings.warn("bf16 steps compiled on a CPU run 256-bit code (compile_model): "
                          "on narrow networks slower than float32 compiled (the command-line "
                          "guide, Training on a CPU)", stacklevel=2)
        self.train_net = compile_model(self.net, bf16_on_cpu) if config.compile else self.net

        self.train_set = self.task.dataset(data, data.train_frames, False, config.seed,
                                           photon_range=tuple(config.photon_range),
                                           **sampling)  # fmt: skip
        per_epoch = config.patches_per_epoch or len(self.train_set)
        origins = self.task.origins(self.train_set)
        group = config.same_origin if origins > 1 else 1  # whole frames: nothing to share
        self.sampler = EpochSampler(len(self.train_set), per_epoch, config.seed,
                                    self.dist.rank, self.dist.world_size, group, origins)
        self.steps_per_epoch = len(self.sampler) // config.batch_size
        if self.steps_per_epoch < 1:
            raise ValueError(
                f"{len(self.sampler)} patches per process and epoch make no batch of "
                f"{config.batch_size}: raise patches_per_epoch or lower batch_size"
            )
        self.val_set = self.task.dataset(data, data.val_frames, True, config.seed, **sampling)
        val_indices = np.arange(len(self.val_set))
        if config.val_patches is not None and config.val_patches < len(val_indices):
            rng = np.random.default_rng(derive_seed(config.seed, 5))
            val_indices = np.sort(rng.choice(val_indices, config.val_patches, replace=False))
        self.val_indices = val_indices[self.dist.rank :: self.dist.world_size].tolist()
        self.val_total = len(val_indices)

        self.optimizer = torch.optim.Adam(self.model.parameters(), lr=config.lr)
        self.scheduler = torch.optim.lr_scheduler.LambdaLR(
            self.optimizer, _WarmupCosine(config.warmup_steps,
                                          config.epochs * self.steps_per_epoch,
                                          config.min_lr_ratio)
        )
        self.epoch = 0  # completed epochs
        self.global_step = 0
        self.history: list[dict[str, float]] = []
        self.step_losses: list[float] = []
        self.best: dict[str, float] = {}

    # ------------------------------------------------------------------ steps
    def _to_device(self, batch: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        return {k: v.to(self.device, non_blocking=True) if k != "origin" else v
                for k, v in batch.items()}

    def _forward(
        self, net: torch.nn.Module, batch: dict[str, torch.Tensor], autocast: bool = False
    ) -> Stages:
        with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=autocast):
            return self.task.outputs(net, batch, self.system)

    def _loss_weights(self, batch: dict[str, torch.Tensor]) -> torch.Tensor | None:
        """Per-pixel weights of the squared error (:func:`~.loss.field_weights`), or
        ``None`` when every pixel weighs the same. Samples without an origin are whole
        sub-views."""
        config = self.config
        if config.edge_weight == config.ring_weight == config.partial_weight == 1.0:
            return None
        target = batch["object"]
        origins = batch.get("origin", torch.zeros(len(target), 2, dtype=torch.int64))
        weights = field_weights(origins, target.shape[-1], self.system.sub_view_size,
                                config.edge_weight, config.ring_weight,
                                partial=config.partial_weight, seen_by_all=self.seen_by_all)
        return weights.to(target.device)

    @property
    def metrics(self) -> tuple[str, ...]:
        """Validation metrics: the loss, then PSNR and SSIM of the reconstruction and of
        every other stage."""
        order = ["recon", *(s for s in self.stages if s != "recon")]
        return ("loss", *(f"{s}_{m}" for s in order for m in ("psnr", "ssim")))

    def train_step(self, batch: dict[str, torch.Tensor]) -> dict[str, float]:
        """One optimisation step on a collated batch; returns the loss parts.

        Raises
        ------
        FloatingPointError
            If the loss or its gradients are NaN or infinite (training diverged; lower
            the learning rate); the weights are left as they were.
        """
        batch = self._to_device(batch)
        self.net.train()
        loss, parts = joint_loss(self._forward(self.train_net, batch, self.autocast),
                                 self.config.alpha,
                                 self.config.beta, self._loss_weights(batch))
        value = float(loss.detach())
        if not math.isfinite(value):
            raise FloatingPointError(
                f"the loss became {value} at step {self.global_step}: training "
                "diverged; lower --lr or check the data"
            )
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        grad_norm = torch.nn.utils.clip_grad_norm_(self.model.parameters(), self.config.grad_clip)
        if not math.isfinite(float(grad_norm)):  # before the update: the weights stay sound
            raise FloatingPointError(
                f"the gradients became non-finite at step {self.global_step} (the loss was "
                f"{value:.4g}): training diverged; lower --lr"
                + (", or train without --compile" if self.config.compile else "")
            )
        self.optimizer.step()
        self.scheduler.step()
        self.global_step += 1
        return {"loss": value, **parts, "grad_norm": float(grad_norm)}

    def train_epoch(self, epoch: int) -> dict[str, float]:
        """Run one epoch's steps; returns the mean loss parts over all processes."""
        self.sampler.set_epoch(epoch)
        loader = torch.utils.data.DataLoader(
            self.train_set, batch_size=self.config.batch_size, sampler=self.sampler,
            drop_last=True, num_workers=self.config.workers, collate_fn=self.task.collate,
        )
        keys = ("loss", *self.stages, "grad_norm")
        sums = torch.zeros(len(keys), dtype=torch.float64)
        bar = tqdm(loader, total=self.steps_per_epoch, desc=f"epoch {epoch + 1}/"
                   f"{self.config.epochs}", disable=not self.progress, leave=False)
        for batch in bar:
            parts = self.train_step(batch)
            self.step_losses.append(parts["loss"])
            sums += torch.tensor([parts[key] for key in keys], dtype=torch.float64)
            bar.set_postfix(loss=f"{parts['loss']:.4f}",
                            lr=f"{self.scheduler.get_last_lr()[0]:.2e}")
        sums = all_reduce_sum(sums.to(self._reduce_device), self.dist).cpu()
        sums /= self.steps_per_epoch * self.dist.world_size
        names = ("train_loss", *(f"train_{s}" for s in self.stages), "grad_norm")
        return dict(zip(names, sums.tolist(), strict=True))

    @property
    def _reduce_device(self) -> torch.device:
        on_gpu = self.dist.active and self.device.type == "cuda"
        return self.device if on_gpu else torch.device("cpu")

    @torch.no_grad()
    def validate(self, bf16: bool = False) -> dict[str, float]:
        """Loss, PSNR and SSIM of every stage (:attr:`metrics`) on the fixed validation
        samples (fixed noise), averaged over samples and processes; the forward pass in
        float32, or in bf16 as an SV-CoDe reconstruction runs it on this device (the
        features in bf16 on the CPU, autocast elsewhere)."""
        self.model.eval()
        net, features = bf16_network(self.model, self.device) if bf16 else (self.model, None)
        autocast = bf16 and features is None
        names = self.metrics
        sums = torch.zeros(len(names) + 1, dtype=torch.float64)
        size = self.config.batch_size
        with self.task.evaluating(net):
            for start in range(0, len(self.val_indices), size):
                items = [self.val_set[i] for i in self.val_indices[start : start + size]]
                batch = self._to_device(self.task.collate(items))
                if features is not None:
                    batch["views"] = batch["views"].to(features)
                stages = self._forward(net, batch, autocast)
                loss, _ = joint_loss(stages, self.config.alpha, self.config.beta,
                                     self._loss_weights(batch))
                n = len(items)
                values = {"loss": float(loss) * n}
                gain = batch["gain"].view(-1, 1, 1, 1)  # scored in the frame's own units
                field = self.task.field_part(batch, self.system)
                for stage, (prediction, target) in stages.items():
                    prediction, target = prediction / gain, target / gain
                    pairs = [(prediction, target)]
                    if stage == "recon" and field is not None:  # each patch's part in the field
                        pairs = [(prediction[i, None, :, r, c], target[i, None, :, r, c])
                                 for i, (r, c) in enumerate(field)]
                    values[f"{stage}_psnr"] = sum(float(psnr_per_sample(*pair).sum())
                                                  for pair in pairs)  # fmt: skip
                    values[f"{stage}_ssim"] = sum(float(ssim_per_sample(*pair).sum())
                                                  for pair in pairs)  # fmt: skip
                sums += torch.tensor([values[name] for name in names] + [n], dtype=torch.float64)
        sums = all_reduce_sum(sums.to(self._reduce_device), self.dist).cpu()
        count = max(sums[-1].item(), 1.0)
        return {f"val_{name}": sums[i].item() / count for i, name in enumerate(names)}

    # ---------------------------------------------------------------- the run
    def fit(self, resume: bool = False) -> list[dict[str, float]]:
        """Train for ``config.epochs`` epochs (the remaining ones when resuming).

        Parameters
        ----------
        resume : bool
            Continue from the run folder's latest checkpoint.

        Returns
        -------
        list of dict
            The per-epoch history.

        Raises
        ------
        FileNotFoundError
            ``resume`` without a checkpoint in the run folder.
        """
        if self.dist.is_main:
            self.out.mkdir(parents=True, exist_ok=True)
        barrier(self.dist)
        if resume:
            self.load_checkpoint()
            best_is_latest = self.best.get("epoch") == self.epoch
            if self.dist.is_main and best_is_latest and not (self.out / BEST).is_file():
                self._save_best()  # a kept resume state leaves out the checkpoint's own weights
        for epoch in range(self.epoch, self.config.epochs):
            start, cpu_start = time.perf_counter(), time.process_time()
            record: dict[str, float] = {"epoch": epoch + 1}
            record.update(self.train_epoch(epoch))
            record.update(self.validate())
            record["lr"] = self.scheduler.get_last_lr()[0]
            record["step"] = self.global_step
            record["seconds"] = round(time.perf_counter() - start, 3)
            record["cpu_seconds"] = round(time.process_time() - cpu_start, 3)  # all threads
            self.history.append(record)
            self.epoch = epoch + 1
            improved = not self.best or record["val_recon_psnr"] > self.best["val_recon_psnr"]
            if improved:  # on every process: the bf16 check validates
                self.best = {**record, **self._bf16_check()}
            if self.dist.is_main:
                if improved:
                    self._save_best()
                self.save_checkpoint()
                self._write_logs()
                if self.progress:
                    tqdm.write(_summary(record))
            barrier(self.dist)
        return self.history

    def _metadata(self) -> dict[str, Any]:
        return {
            "system": self.system.name,
            "model_config": self.model_config.to_dict(),
            "train_config": self.config.to_dict(),
            "data": {"path": str(self.data.path.resolve()),
                     "recipe": self.data.manifest["recipe"],
                     "train_frames": len(self.data.train_frames),
                     "val_frames": len(self.data.val_frames),
                     f"train_{self.task.unit}": len(self.train_set),
                     f"val_{self.task.unit}": self.val_total},
            "world_size": self.dist.world_size,
            "device": str(self.device),
        }

    def _bf16_check(self) -> dict[str, float]:
        """SV-CoDe on a device with bf16 units: the validation reconstruction PSNR in bf16
        (as reconstructions run it), from which the model file's ``precision_check`` is
        written (what ``precision="auto"`` reads when reconstructing); else nothing."""
        if self.task.unit != "patches" or not native_bf16(self.device):
            return {}
        return {"val_recon_psnr_bf16": self.validate(bf16=True)["val_recon_psnr"]}

    def _save_best(self) -> None:
        extra = {**self._metadata(), **self.inherited, "epoch": self.best["epoch"],
                 "metrics": self.best}
        if "val_recon_psnr_bf16" in self.best:
            loss = self.best["val_recon_psnr"] - self.best["val_recon_psnr_bf16"]
            extra["precision_check"] = {"bf16": {
                "loss_db": round(loss, 4), "measured_on": f"{self.val_total} validation "
                f"{self.task.unit} of {self.data.path.name}, epoch {self.best['epoch']}"}}
        _atomic_write(self.out / BEST, lambda tmp: save_model(tmp, self.model, self.system, extra))

    # ------------------------------------------------------------ checkpoints
    def save_checkpoint(self) -> Path:
        """Write the checkpoint of the completed epochs and point ``latest.json`` at it."""
        folder = self.out / CHECKPOINTS
        folder.mkdir(parents=True, exist_ok=True)
        name = f"epoch-{self.epoch:04d}"
        weights, state_path = folder / f"{name}.safetensors", folder / f"{name}.pt"
        state = {
            "epoch": self.epoch,
            "global_step": self.global_step,
            "optimizer": self.optimizer.state_dict(),
            "scheduler": self.scheduler.state_dict(),
            "torch_rng": torch.get_rng_state(),
            "cuda_rng": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else [],
            "history": self.history,
            "step_losses": self.step_losses,
            "best": self.best,
            "model_config": self.model_config.to_json(),
            "train_config": json.dumps(self.config.to_dict()),
        }
        _atomic_write(weights, lambda tmp: save_model(tmp, self.model, self.system,
                                                      {"epoch": self.epoch, **self.inherited}))
        _atomic_write(state_path, lambda tmp: torch.save(state, tmp))
        previous = self._latest(strict=False)  # a damaged one is replaced here
        write_text_atomic(folder / LATEST, json.dumps(
            {"epoch": self.epoch, "weights": weights.name, "state": state_path.name}) + "\n")
        if previous is not None and previous.get("epoch") != self.epoch:
            for key in ("weights", "state"):
                (folder / previous[key]).unlink(missing_ok=True)
        return weights

    def _load_initial_weights(self, path: Path) -> None:
        source, _ = load_model(path)
        config = self.model_config
        if isinstance(config, ModelConfig) and isinstance(source, SVCoDe):
            config = config.replace(padding=source.model_config.padding,  # these change
                                    view_margin=source.model_config.view_margin)  # no weights
            if (source.model_config.views_per_lens < config.views_per_lens
                    and source.model_config.replace(lens_context=True,
                                                    context_reach=config.context_reach) == config):
                # fine-tuning that adds the lens context or lengthens its reach
                source = with_lens_context(source, config.context_reach)
        if type(source) is not type(self.model) or source.model_config != config:
            raise ValueError(f"{path}: a {type(source).__name__} model of another network "
                             f"configuration than this run's {type(self.model).__name__}")
        try:
            self.model.load_state_dict(source.state_dict())
        except RuntimeError as error:  # frame-sized filters of another system's size
            raise ValueError(f"{path}: its weights do not fit this dataset's system: "
                             f"{str(error).splitlines()[-1].strip()}") from error
        check = getattr(source, "overlap_check", {})
        if check:  # fine-tuning keeps the receptive field: its measured overlap still plans tiles
            self.inherited["overlap_check"] = {**check, "inherited_from": path.name}

    def _latest(self, strict: bool = True) -> dict[str, Any] | None:
        """``latest.json`` (``None`` if there is none); a damaged one raises
        :class:`ValueError`, or with ``strict=False`` counts as none."""
        path = self.out / CHECKPOINTS / LATEST
        if not path.is_file():
            return None
        try:
            latest = json.loads(path.read_text(encoding="utf-8"))
            if not all(isinstance(latest.get(key), str) for key in ("weights", "state")):
                raise ValueError("it does not name the checkpoint's weights and state files")
        except (ValueError, AttributeError) as err:  # (UnicodeDecodeError is a ValueError)
            if not strict:
                return None
            reason = str(err) if isinstance(err, ValueError) else "not a JSON object"
            raise ValueError(f"{path} is damaged ({reason}): {_RESTART}") from None
        return latest

    def load_checkpoint(self) -> int:
        """Restore the latest checkpoint of the run folder; returns its epoch.

        Raises
        ------
        FileNotFoundError
            If the run folder has no checkpoint.
        ValueError
            If the checkpoint was written with another model or training configuration.
        """
        latest = self._latest()
        if latest is None:
            raise FileNotFoundError(f"no checkpoint to resume from in {self.out / CHECKPOINTS}")
        folder = self.out / CHECKPOINTS
        state = _read_checkpoint(folder / latest["state"], lambda path: torch.load(
            path, map_location="cpu", weights_only=True))  # fmt: skip
        for key, config in (("model_config", self.model_config), ("train_config", self.config)):
            stored = _with_defaults(config, json.loads(state[key]))
            current = json.loads(json.dumps(config.to_dict()))
            stored.pop("compile", None), current.pop("compile", None)  # speed only
            if stored != current:
                differing = sorted(k for k in {**stored, **current}
                                   if stored.get(k) != current.get(k))
                raise ValueError(f"the checkpoint in {folder} was written with another "
                                 f"{key.replace('_', ' ')} (differs in {differing}); resume "
                                 "with the original settings or start a new run folder")
        weights = _read_checkpoint(folder / latest["weights"],
                                   lambda path: load_file(str(path), device=str(self.device)))
        self.model.load_state_dict(weights, strict=True)
        self.optimizer.load_state_dict(state["optimizer"])
        self.scheduler.load_state_dict(state["scheduler"])
        torch.set_rng_state(state["torch_rng"])
        if state["cuda_rng"] and torch.cuda.is_available():
            torch.cuda.set_rng_state_all(state["cuda_rng"])
        self.epoch, self.global_step = state["epoch"], state["global_step"]
        self.history, self.step_losses = state["history"], state["step_losses"]
        self.best = state["best"]
        return self.epoch

    # ------------------------------------------------------------------- logs
    def _write_logs(self) -> None:
        columns = list(self.history[0])
        text = io.StringIO()
        writer = csv.DictWriter(text, fieldnames=columns, lineterminator="\n")
        writer.writeheader()
        writer.writerows(self.history)
        write_text_atomic(self.out / "log.csv", text.getvalue())
        log = {**self._metadata(), "history": self.history, "best": self.best,
               "step_losses": self.step_losses}
        write_text_atomic(self.out / "log.json", json.dumps(log, indent=1) + "\n")
        _atomic_write(self.out / "loss.png", lambda tmp: self.plot(tmp))

    def plot(self, path: str | Path) -> None:
        """Loss curves (per step and per epoch, train and validation) and validation PSNR."""
        from matplotlib.backends.backend_agg import FigureCanvasAgg  # only when drawing
        from matplotlib.figure import Figure

        figure = Figure(figsize=(9, 3.6), layout="constrained")
        FigureCanvasAgg(figure)
        ax_loss, ax_psnr = figure.subplots(1, 2)
        steps = np.arange(1, len(self.step_losses) + 1)
        ax_loss.plot(steps, self.step_losses, color="0.75", lw=0.8, label="train (step)")
        epoch_steps = [r["step"] for r in self.history]
        ax_loss.plot(epoch_steps, [r["train_loss"] for r in self.history], "o-",
                     label="train (epoch mean)")
        ax_loss.plot(epoch_steps, [r["val_loss"] for r in self.history], "s-",
                     label="validation")
        ax_loss.set(xlabel="step", ylabel="loss  Σ α(1−SSIM) + β·MSE", yscale="log")
        ax_loss.legend()
        epochs = [r["epoch"] for r in self.history]
        labels = {"recon": "reconstruction", "demix": "demixed views"}
        for stage, marker in zip(self.stages[::-1], "os", strict=False):
            ax_psnr.plot(epochs, [r[f"val_{stage}_psnr"] for r in self.history], f"{marker}-",
                         label=labels.get(stage, stage))
        ax_psnr.set(xlabel="epoch", ylabel="validation PSNR (dB)")
        ax_psnr.legend()
        figure.suptitle(f"{self.task.label} training on {self.system.name}")
        figure.savefig(path, format="png", dpi=100)


def _summary(record: dict[str, float]) -> str:
    demix = (f", demix PSNR {record['val_demix_psnr']:.2f} dB"
             if "val_demix_psnr" in record else "")
    return (f"epoch {record['epoch']}: train {record['train_loss']:.4f}, val "
            f"{record['val_loss']:.4f}, recon PSNR {record['val_recon_psnr']:.2f} dB / "
            f"SSIM {record['val_recon_ssim']:.3f}{demix} ({record['seconds']:.0f} s)")
