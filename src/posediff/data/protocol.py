"""What a data module tells the commands, so that ``posediff fit / eval / predict`` only instantiate
and call (docs/extending.md, "How to add a dataset"). A Lightning ``LightningDataModule`` with these members:

``scorer`` (class attribute)
    which scorer of :data:`posediff.evaluation.SCORERS` scores its test split: ``"shapes"`` (spread,
    translation error, coverage per shape: the toys, SYMSOL) or ``"bop"`` (the BOP19 protocol).
``shapes``
    the names of the rows of the per-shape / per-object tables.
``describe() -> str``
    one line on what was read (``fit`` and ``eval`` print it).
``checkpoint_data() -> dict``
    data settings a checkpoint must carry to evaluate without the training split (BOP: the
    translation statistics); merged into the stored ``data`` config.
``results_filename(tag) -> str | None``
    the name of the file its estimates are written to (BOP: the toolkit's
    ``METHOD_DATASET-SPLIT.csv``), or None.
``prediction_input(index) -> dict``
    what ``posediff predict index=N`` needs for test sample N: ``image`` (the network's input),
    ``gt_pose``, and optionally ``decode`` (network poses → camera frame), ``K`` (of ``image``),
    ``camera_offset``, ``shape``, ``mesh``, ``gt_rotations``, ``mode_translation_radius``, ``info``.
``image_camera(data_config) -> (K, camera_offset)`` (class method)
    the camera of an arbitrary input image (``predict image=…``), or ``(None, None)``;
``log_likelihood_default`` (optional, default False)
    whether evaluations report the ground truth's log density when ``eval.log_likelihood`` is null
    (SYMSOL: yes).
``needs_test_target`` (class attribute)
    True when a prediction needs a test target's box and camera (BOP), so ``image=`` is refused.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, ClassVar, Protocol, runtime_checkable


@runtime_checkable
class PoseDataModule(Protocol):
    """The members above (module docstring)."""

    scorer: ClassVar[str]
    needs_test_target: ClassVar[bool]
    shapes: Sequence[str]

    def describe(self) -> str: ...

    def checkpoint_data(self) -> dict[str, Any]: ...

    def results_filename(self, tag: str = "") -> str | None: ...

    def prediction_input(self, index: int) -> dict[str, Any]: ...

    @classmethod
    def image_camera(cls, data_config: Mapping[str, Any]) -> tuple[Any, Any]: ...


class LoaderPredictions:
    """The common parts of the protocol for data modules whose test loader yields ``image`` (or the
    condition), ``pose`` and ``shape`` (an index into ``shapes``): mixed into the toy and SYMSOL."""

    scorer: ClassVar[str] = "shapes"
    needs_test_target: ClassVar[bool] = False

    def checkpoint_data(self) -> dict[str, Any]:
        return {}

    def results_filename(self, tag: str = "") -> str | None:
        return None

    def test_sample(self, index: int) -> dict[str, Any]:
        """Test sample ``index`` in loader order (the order eval uses)."""
        n = 0
        for batch in self.test_dataloader():  # type: ignore[attr-defined]
            b = int(batch["pose"].shape[0])
            if index < n + b:
                return {k: v[index - n] for k, v in batch.items()}
            n += b
        raise IndexError(f"index={index} but the test data has {n} samples")

    @classmethod
    def image_camera(cls, data_config: Mapping[str, Any]) -> tuple[Any, Any]:
        return None, None


__all__ = ["LoaderPredictions", "PoseDataModule"]
