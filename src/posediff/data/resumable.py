"""A training ``DataLoader`` that resumes mid-epoch exactly (Lightning's stateful-loader interface).

Lightning 2.x stores ``state_dict()`` of every training loader that has ``state_dict`` /
``load_state_dict`` in the checkpoint (``loops.fit_loop.state_dict.combined_loader``) and, on
``trainer.fit(ckpt_path=...)``, calls ``load_state_dict`` before it creates the first iterator.
A plain ``DataLoader`` has neither, so a resumed run restarts the epoch from its first batch, with
a permutation drawn afresh. :class:`ResumableDataLoader` makes the data order a function of
``(seed, pass, position)`` only:

* **pass** (epoch): the loader counts its own passes (one ``iter()`` per pass; Lightning makes one
  per epoch). Pass ``e`` of a shuffled map-style dataset is the permutation of torch's
  ``DistributedSampler`` for ``seed`` and epoch ``e`` (one rank's share under DDP).
* **position**: the batches handed out in the current pass. A sized loader is not prefetched by
  Lightning's fit loop, so at checkpoint time that is exactly the number of batches trained on.
  On restore the sampler skips that many batches' samples (map-style: free); an iterable dataset
  is advanced by drawing and discarding them.
* **per-sample randomness**: before each pass the dataset's ``set_epoch(e)`` is called when it
  has one (datasets derive their augmentation from ``(seed, epoch, index)``, never from the
  global or the worker RNG, whose streams a resume changes), and the loader's own generator is
  reseeded from ``(seed, e)``, so worker base seeds do not depend on the global RNG either.

Iterator creation never draws from the global torch RNG (the loader has its own generator), so
loading data does not shift the noise stream of the training steps.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import torch
from torch.utils.data import DataLoader, Dataset, DistributedSampler, IterableDataset

__all__ = ["ResumableDataLoader", "ResumableSampler", "eval_loader"]


def _rank_world() -> tuple[int, int]:
    if torch.distributed.is_available() and torch.distributed.is_initialized():
        return torch.distributed.get_rank(), torch.distributed.get_world_size()
    return 0, 1


class ResumableSampler(DistributedSampler):
    """torch's ``DistributedSampler`` (permutation of epoch ``e`` seeded by ``seed + e``; one rank's
    share; Lightning leaves such a sampler alone under DDP) that can skip the first ``skip`` samples
    of its next pass (set by :meth:`ResumableDataLoader.load_state_dict`). ``len`` is always the
    whole pass: Lightning counts the batches of a resumed epoch from where it stopped."""

    def __init__(self, dataset: Dataset, *, shuffle: bool, seed: int) -> None:
        rank, world = _rank_world()
        super().__init__(dataset, num_replicas=world, rank=rank, shuffle=shuffle, seed=int(seed))
        self.skip = 0

    def __iter__(self) -> Iterator[int]:
        indices = list(super().__iter__())
        skip, self.skip = self.skip, 0
        return iter(indices[skip:])


class ResumableDataLoader(DataLoader):
    """A ``DataLoader`` whose data order is a function of ``(seed, pass, position)`` and that Lightning
    checkpoints and restores mid-pass (module docstring). Takes ``DataLoader``'s keyword arguments
    except ``sampler`` / ``batch_sampler`` / ``generator``; ``shuffle`` applies to map-style datasets
    (an iterable dataset shuffles itself from ``set_epoch``)."""

    def __init__(
        self,
        dataset: Dataset,
        *,
        batch_size: int = 1,
        shuffle: bool = False,
        seed: int = 0,
        drop_last: bool = False,
        **kwargs: Any,
    ) -> None:
        self._iterable = isinstance(dataset, IterableDataset)
        sampler = None if self._iterable else ResumableSampler(dataset, shuffle=shuffle, seed=seed)
        super().__init__(
            dataset,
            batch_size=batch_size,
            sampler=sampler,
            drop_last=drop_last,
            generator=torch.Generator(),
            **kwargs,
        )
        self.seed = int(seed)
        self._epoch = 0  # the pass the next iter() starts
        self._skip = 0  # batches of that pass to skip (after load_state_dict)
        self._live: list[int] | None = None  # [pass, batches handed out] of the current iterator

    def __iter__(self) -> Iterator[Any]:  # type: ignore[override]
        epoch, skip = self._epoch, self._skip
        self._epoch, self._skip = epoch + 1, 0
        if isinstance(self.sampler, ResumableSampler):
            self.sampler.set_epoch(epoch)
            self.sampler.skip = skip * int(self.batch_size or 1)
        if callable(getattr(self.dataset, "set_epoch", None)):
            self.dataset.set_epoch(epoch)
        self.generator.manual_seed(self.seed * 1_000_003 + epoch)  # worker base seeds of this pass
        live = [epoch, skip]
        self._live = live
        it = super().__iter__()
        if self._iterable:  # no sampler to skip with: draw and drop what was trained on
            for _ in range(skip):
                next(it)
        return _Counting(it, live)

    def state_dict(self) -> dict[str, int]:
        """``{"epoch": pass, "batches": position, "num_batches": len}`` of the current pass (a pass
        handed out in full is stored as the start of the next)."""
        epoch, batches = self._live if self._live is not None else (self._epoch, self._skip)
        n = len(self)
        if batches >= n:
            epoch, batches = epoch + 1, 0
        return {"epoch": int(epoch), "batches": int(batches), "num_batches": int(n)}

    def load_state_dict(self, state: dict[str, int]) -> None:
        """Continue at pass ``state["epoch"]``, after its first ``state["batches"]`` batches."""
        n = int(state.get("num_batches", len(self)))
        if n != len(self):
            raise ValueError(
                f"cannot resume the training data mid-epoch: the checkpoint's epoch had {n} batches, "
                f"this data has {len(self)} (the data or batch size changed)"
            )
        self._epoch, self._skip, self._live = int(state["epoch"]), int(state["batches"]), None


class _Counting(Iterator[Any]):
    """Counts the batches an iterator hands out into ``live[1]``."""

    def __init__(self, it: Iterator[Any], live: list[int]) -> None:
        self._it, self._live = it, live

    def __next__(self) -> Any:
        batch = next(self._it)
        self._live[1] += 1
        return batch

    def __len__(self) -> int:
        return len(self._it)  # type: ignore[arg-type]


def eval_loader(dataset: Dataset, *, batch_size: int, num_workers: int = 0, **kwargs: Any) -> DataLoader:
    """An unshuffled loader for validation / test with its own generator: iterating it never draws
    from the global torch RNG (a plain ``DataLoader`` draws its base seed there), so validation
    does not move the training noise stream."""
    return DataLoader(
        dataset,
        batch_size=batch_size,
        shuffle=False,
        num_workers=num_workers,
        generator=torch.Generator().manual_seed(0),
        **kwargs,
    )
