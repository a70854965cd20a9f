"""Which samples each optimiser step trains on: the frame of every slot of an epoch, this rank's slots of every global
batch, and the loader that turns those keys into augmented batches.

Epoch ``e`` has ``samples_per_epoch`` slots. Slot ``k`` holds frame ``k mod N`` (the reference's unshuffled loop), or
with ``train.shuffle`` the ``k``-th frame of a permutation seeded by ``(seed, e)``; it is augmented with the generator
``(seed, e, k)``. Step ``s`` takes the global batch of slots ``[s*G, (s+1)*G)`` with ``G = batch_size * world_size``;
rank ``r`` takes the ``r``-th per-rank slice. Nothing depends on the worker, the rank count or a resume.

Bad input met while loading (a NaN in a scan, a label the pre-run check cannot see) is the same one-line
:class:`InputError` with or without DataLoader workers: a worker hands it back as a :class:`LoadFailure` in place of
the batch and the main process raises it, where torch would re-raise it with the worker's traceback in its message.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator, Sequence

import numpy as np
import torch

from detector.data import Batch, Sample, TrainingSet, collate
from mpchair.core.errors import InputError

#: One sample of an epoch: ``(epoch, slot, frame index)``.
SlotKey = tuple[int, int, int]


def epoch_frames(*, num_frames: int, samples_per_epoch: int, epoch: int, seed: int, shuffle: bool) -> np.ndarray:
    """(S,) int64 frame index of every slot of epoch ``epoch`` (see the module docstring for the rule)."""
    if shuffle:
        rng = np.random.Generator(np.random.PCG64(np.random.SeedSequence([int(seed), int(epoch), 0x5EED])))
        reps = -(-samples_per_epoch // num_frames)
        order = np.concatenate([rng.permutation(num_frames) for _ in range(reps)])
        return order[:samples_per_epoch].astype(np.int64)
    return (np.arange(samples_per_epoch) % num_frames).astype(np.int64)


def rank_batches(
    frames: np.ndarray, *, epoch: int, global_batch: int, rank: int, per_rank: int, start_step: int
) -> list[list[SlotKey]]:
    """Per-step lists of keys ``(epoch, slot, frame)`` for this rank, from step ``start_step`` on (last partial
    global batch dropped, so every rank runs the same number of steps)."""
    steps = len(frames) // global_batch
    out = []
    for s in range(start_step, steps):
        slots = range(s * global_batch + rank * per_rank, s * global_batch + (rank + 1) * per_rank)
        out.append([(epoch, k, int(frames[k])) for k in slots])
    return out


@dataclasses.dataclass(frozen=True)
class LoadFailure:
    """An :class:`InputError` met while loading a sample, as plain picklable fields (it crosses from a worker)."""

    message: str
    path: str | None
    line: int | None

    def error(self) -> InputError:
        """The error again, with the same one-line message."""
        return InputError(self.message, self.path, self.line)


class SlotDataset(torch.utils.data.Dataset):
    """Keys ``(epoch, slot, frame)`` → the augmented sample; slot ``k`` is augmented with generator (seed, epoch, k).
    Bad input gives a :class:`LoadFailure` instead of raising (see the module docstring)."""

    def __init__(self, base: TrainingSet) -> None:
        self.base = base

    def __len__(self) -> int:
        return len(self.base)

    def __getitem__(self, key: SlotKey) -> Sample | LoadFailure:
        epoch, slot, frame = key
        try:
            return self.base.sample(epoch, slot, frame)
        except InputError as e:
            return LoadFailure(e.message, e.path, e.line)


def collate_or_failure(items: Sequence[Sample | LoadFailure]) -> Batch | LoadFailure:
    """The batch of ``items``, or the first :class:`LoadFailure` among them."""
    for item in items:
        if isinstance(item, LoadFailure):
            return item
    return collate(items)


def rank_loader(keys: list[list[SlotKey]], base: TrainingSet, workers: int, pin: bool = False) -> Iterator[Batch]:
    """The collated batches of ``keys`` (one list of keys per step), loaded by ``workers`` processes (0: this one);
    ``pin``: in page-locked memory, for a fast non-blocking copy to a GPU (:func:`detector.device.pin_memory`)."""
    if not keys:
        return iter(())
    # Its own generator: every DataLoader iterator draws its workers' base seed from one, and the global one would
    # then advance once per loader, so a resumed run (one more loader: the rest of the cut epoch) would save another
    # RNG state in its checkpoints than the uninterrupted run. Samples never use it (slot k: generator (seed, epoch,
    # k)).
    loader = torch.utils.data.DataLoader(
        SlotDataset(base), batch_sampler=keys, collate_fn=collate_or_failure, num_workers=workers, pin_memory=pin,
        generator=torch.Generator().manual_seed(0),
    )
    return _raise_failures(iter(loader))


def _raise_failures(batches: Iterator[Batch | LoadFailure]) -> Iterator[Batch]:
    """``batches`` up to the first :class:`LoadFailure`, which is raised here (in the main process)."""
    for batch in batches:
        if isinstance(batch, LoadFailure):
            raise batch.error()
        yield batch
