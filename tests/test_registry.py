"""The group registry: filled by subclassing, read-only, kept in sync with conf/group/."""

from pathlib import Path

import pytest
import torch
import yaml
from hydra.utils import get_class, instantiate
from omegaconf import OmegaConf

from posediff.lie import SE3, SO3, LieGroup, UnknownNameError, get_group

CONF = Path(__file__).resolve().parents[1] / "conf"


def test_get_group_returns_instances() -> None:
    assert isinstance(get_group("se3"), SE3)
    assert get_group("so3") == SO3()
    assert get_group("so3", compiled=True).compiled


def test_unknown_group_lists_registered_names() -> None:
    with pytest.raises(UnknownNameError) as err:
        get_group("sim3")
    msg = str(err.value)
    assert msg.startswith("unknown Lie group 'sim3'") and "\n" not in msg
    for name in ("so3", "r3so3", "se3", "se2"):
        assert name in msg


def test_registry_is_read_only() -> None:
    with pytest.raises(TypeError):
        LieGroup.registry["x"] = SO3  # type: ignore[index]


def test_subclass_with_name_registers_itself() -> None:
    class Mirror(SO3, name="mirror_test"):
        pass

    try:
        assert LieGroup.registry["mirror_test"] is Mirror
        assert isinstance(get_group("mirror_test"), Mirror)
        with pytest.raises(TypeError, match="already registered"):

            class Other(SO3, name="mirror_test"):
                pass
    finally:
        LieGroup._entries.pop("mirror_test", None)


def test_subclass_without_name_is_not_registered() -> None:
    before = dict(LieGroup.registry)

    class Helper(SO3):
        pass

    assert dict(LieGroup.registry) == before


def test_named_group_must_define_dimensions() -> None:
    with pytest.raises(TypeError, match="must define"):

        class Broken(LieGroup, name="broken_test"):
            pass

    LieGroup._entries.pop("broken_test", None)


def test_conf_groups_match_registry() -> None:
    """conf/group/<name>.yaml ↔ registry entry <name>, and its _target_ is that class."""
    files = {p.stem: p for p in (CONF / "group").glob("*.yaml")}
    assert set(files) == set(LieGroup.registry)
    for name, path in files.items():
        cfg = yaml.safe_load(path.read_text())
        assert get_class(cfg["_target_"]) is LieGroup.registry[name]
        group = instantiate(OmegaConf.create(cfg))
        assert type(group) is LieGroup.registry[name] and not group.compiled


def test_group_equality_and_repr() -> None:
    assert SE3() == SE3() and SE3() != SO3() and SE3() != SE3(compiled=True)
    assert repr(SE3()) == "SE3()" and repr(SE3(compiled=True)) == "SE3(compiled=True)"
    assert len({SE3(), SE3(), SO3()}) == 2


def test_identity_and_sample_uniform_arguments() -> None:
    g = SE3()
    assert g.identity(5).shape == (5, 4, 4)
    assert g.identity((2, 3), dtype=torch.float32).dtype == torch.float32
    gen = torch.Generator().manual_seed(1)
    x = g.sample_uniform(100, generator=gen, bound=0.25)
    assert x[..., :3, 3].abs().max() <= 0.25
