"""One process's place in a torchrun job and the collective operations training needs: differentiable all-reduce,
global-batch BatchNorm statistics, sums over ranks, barriers, the process group's lifetime.

Outside a torchrun job (world size 1, no process group) every operation here is the identity / a no-op, so the same
training code runs in one process.
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime
import functools
import os
from collections.abc import Iterator

import torch
import torch.distributed as dist
from torch import nn

from mpchair.core.errors import InputError


@dataclasses.dataclass(frozen=True)
class DistInfo:
    """This process's place in a torchrun job (``rank 0 of 1`` for a plain run)."""

    rank: int = 0
    world_size: int = 1
    local_rank: int = 0

    @property
    def distributed(self) -> bool:
        return self.world_size > 1

    @property
    def is_main(self) -> bool:
        return self.rank == 0


def dist_info_from_env() -> DistInfo:
    """Rank / world size / local rank from the variables torchrun sets (``RANK``, ``WORLD_SIZE``, ``LOCAL_RANK``)."""
    return DistInfo(
        rank=int(os.environ.get("RANK", "0")),
        world_size=int(os.environ.get("WORLD_SIZE", "1")),
        local_rank=int(os.environ.get("LOCAL_RANK", "0")),
    )


def resolve_device(device: str, info: DistInfo) -> torch.device:
    """The torch device of ``--device`` for this process (under torchrun, CUDA device ``LOCAL_RANK``)."""
    if device == "cpu":
        return torch.device("cpu")
    if device == "cuda":
        if not torch.cuda.is_available():
            raise InputError("--device cuda: no CUDA device is available")
        return torch.device("cuda", info.local_rank if info.distributed else torch.cuda.current_device())
    raise InputError(f"unknown device {device!r} (cpu or cuda)")


#: How long the ranks of a job started by hand (not by torchrun) wait for each other before giving up.
JOIN_TIMEOUT_S = 600.0


def _join(info: DistInfo) -> dist.Store | None:
    """The job's key-value store once every rank has joined it, for ranks started without torchrun's agent (which
    rendezvouses itself: None then). A rank whose partners never come is an :class:`InputError` after
    ``DETECTOR_JOIN_TIMEOUT_S`` seconds (default :data:`JOIN_TIMEOUT_S`) instead of a wait of the job's 6 h."""
    if os.environ.get("TORCHELASTIC_USE_AGENT_STORE") == "True":
        return None
    host, port = os.environ["MASTER_ADDR"], int(os.environ["MASTER_PORT"])
    seconds = float(os.environ.get("DETECTOR_JOIN_TIMEOUT_S", JOIN_TIMEOUT_S))
    try:  # the first rank hosts the store and waits for the others to connect; the others connect, retrying
        store = dist.TCPStore(host, port, info.world_size, info.rank == 0, timeout=datetime.timedelta(seconds=seconds),
                              wait_for_workers=True)
    except RuntimeError as e:  # torch's DistStoreError / DistNetworkError
        raise InputError(f"rank {info.rank} of {info.world_size}: the other ranks did not join at {host}:{port} "
                         f"within {seconds:g} s ({' '.join(str(e).split())[:120]}); start every rank (torchrun "
                         "--nproc-per-node=N -m detector train ... does)") from None
    store.set_timeout(datetime.timedelta(hours=6))  # joined: later waits are the job's (see process_group)
    return store


@contextlib.contextmanager
def process_group(info: DistInfo, device: torch.device) -> Iterator[None]:
    """Join torchrun's process group for the block (gloo on CPU, nccl on CUDA) and leave it afterwards; nothing in a
    plain run."""
    if info.distributed and not dist.is_initialized():
        backend = "nccl" if device.type == "cuda" else "gloo"
        if device.type == "cuda":
            torch.cuda.set_device(device)
        # Rank 0 may evaluate or build the GT database while the others wait at a barrier: allow hours, not minutes.
        dist.init_process_group(backend=backend, timeout=datetime.timedelta(hours=6), store=_join(info),
                                rank=info.rank, world_size=info.world_size)
    try:
        yield
    finally:
        if info.distributed and dist.is_initialized():
            dist.destroy_process_group()


def world_active() -> bool:
    """Whether a process group of more than one process is running."""
    return dist.is_available() and dist.is_initialized() and dist.get_world_size() > 1


class _AllReduceSum(torch.autograd.Function):
    """Differentiable sum over ranks: every rank gets the sum, and the gradient of each rank's input is the sum of
    the output gradients of all ranks (each rank's output depends on every input).

    Written here with the public ``dist.all_reduce`` because ``torch.distributed.nn.functional.all_reduce`` is
    deprecated (a FutureWarning per call site and rank) and its suggested replacement is a private module."""

    @staticmethod
    def forward(ctx: torch.autograd.function.FunctionCtx, tensor: torch.Tensor) -> torch.Tensor:
        out = tensor.clone(memory_format=torch.contiguous_format)
        dist.all_reduce(out)
        return out

    @staticmethod
    def backward(ctx: torch.autograd.function.FunctionCtx, grad: torch.Tensor) -> torch.Tensor:
        return _AllReduceSum.apply(grad)


class _GlobalStatsBatchNorm(nn.modules.batchnorm._BatchNorm):
    """Mixin that makes a BatchNorm's training statistics span every process (see :func:`convert_to_global_batchnorm`).

    Mean and biased variance (used to normalise) come from all-reduced sums ``sum x`` and ``sum (x - mean)^2`` over
    all ranks; the all-reduce is differentiable (:class:`_AllReduceSum`), so gradients flow through the statistics
    exactly as in one process. Running buffers get the global mean and the unbiased global variance. Outside
    distributed training it is the ordinary BatchNorm.
    """

    def forward(self, input: torch.Tensor) -> torch.Tensor:
        if not (self.training and world_active()):
            return super().forward(input)
        all_reduce = _AllReduceSum.apply
        self._check_input_dim(input)
        c = input.shape[1]
        dims = [0, *range(2, input.dim())]
        shape = [1, c] + [1] * (input.dim() - 2)
        count = input.new_tensor([input.numel() / max(c, 1)])
        sums = all_reduce(torch.cat([input.sum(dims), count]))
        n = sums[-1]
        mean = sums[:-1] / n
        centred = input - mean.view(shape)
        var = all_reduce(centred.pow(2).sum(dims)) / n
        out = centred * torch.rsqrt(var + self.eps).view(shape)
        if self.affine:
            out = out * self.weight.view(shape) + self.bias.view(shape)
        if self.track_running_stats:
            with torch.no_grad():
                self.num_batches_tracked.add_(1)
                m = self.momentum if self.momentum is not None else 1.0 / float(self.num_batches_tracked)
                self.running_mean.mul_(1 - m).add_(mean.detach() * m)
                unbiased = var.detach() * (n / (n - 1).clamp(min=1))
                self.running_var.mul_(1 - m).add_(unbiased * m)
        return out


@functools.cache
def _global_batchnorm_class(cls: type) -> type:
    """``Global<cls>``: ``cls`` with :class:`_GlobalStatsBatchNorm` right before ``_BatchNorm`` in its MRO (one type
    per BatchNorm class, however many instances are converted)."""
    return type(f"Global{cls.__name__}", (cls, _GlobalStatsBatchNorm), {})


def convert_to_global_batchnorm(model: nn.Module) -> nn.Module:
    """Make every BatchNorm of ``model`` (incl. subclasses such as the sparse active-site BN) use global-batch
    statistics across the process group; returns ``model`` (changed in place).

    Each BN instance gets a subclass of its own class whose MRO puts :class:`_GlobalStatsBatchNorm` right before
    ``_BatchNorm``: a subclass's own ``forward`` (e.g. one that unwraps a ``SparseTensor``) still runs and reaches the
    global statistics through ``super().forward``. Parameters, buffers and ``state_dict`` keys are unchanged.
    (``torch.nn.SyncBatchNorm`` would do the same on GPUs only: it refuses CPU tensors.)
    """
    for module in model.modules():
        if isinstance(module, nn.modules.batchnorm._BatchNorm) and not isinstance(module, _GlobalStatsBatchNorm):
            module.__class__ = _global_batchnorm_class(type(module))
    return model


def all_reduce_sum(values: torch.Tensor) -> torch.Tensor:
    """Sum over ranks (identity in a single process)."""
    if world_active():
        values = values.clone()
        dist.all_reduce(values)
    return values


def barrier() -> None:
    """Wait for every rank (nothing in a single process)."""
    if world_active():
        dist.barrier()
