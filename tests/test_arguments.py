"""The science packages name their arguments, never config keys; the commands name the key where
the user set it (``fusion_depth.config.arguments``)."""

from __future__ import annotations

import ast
import importlib
import re

import pytest
from helpers import REPO, compose_config
from hydra.core.global_hydra import GlobalHydra

from fusion_depth.config import arguments
from fusion_depth.config.hydra_main import _short_errors
from fusion_depth.data.folders import require_root
from fusion_depth.errors import ArgumentError, ArgumentFileError, CommandError

SCIENCE = ("models", "losses", "metrics", "data", "optim")
# A dotted key of a config node, as a message would name it (``dataset.root``, ``loss.w_ssim``).
# Not a file name (``model.safetensors``) nor a parameter name of transformers' Depth Anything
# (``backbone.embeddings.cls_token``, ``backbone.encoder.layer.0``, ``backbone.layernorm``).
CONFIG_KEY = re.compile(
    r"\b(model\.net|model|dataset|loss|optimizer|scheduler|backbone|fusion|augment|data|trainer"
    r"|eval|callbacks|prepare|paths)\.((?!safetensors\b|embeddings\b|encoder\b|layernorm\b)"
    r"[a-z_]+|$)"
)


def _code_strings(source: str) -> list[tuple[int, str]]:
    """The string constants of a module's source that are code, not documentation (docstrings
    and the strings that document an attribute are left out)."""
    tree = ast.parse(source)
    documentation = {
        id(node.value)
        for node in ast.walk(tree)
        if isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant)
    }
    return [
        (node.lineno, node.value)
        for node in ast.walk(tree)
        if isinstance(node, ast.Constant)
        and isinstance(node.value, str)
        and id(node) not in documentation
        and not node.value.startswith("fusion_depth.")
    ]


def test_the_science_packages_name_no_config_key() -> None:
    found = [
        f"{path.relative_to(REPO)}:{line}: {text[:80]!r}"
        for package in SCIENCE
        for path in sorted((REPO / "fusion_depth" / package).rglob("*.py"))
        for line, text in _code_strings(path.read_text(encoding="utf-8"))
        if CONFIG_KEY.search(text)
    ]
    assert found == []


def test_the_check_finds_a_message_that_names_a_key() -> None:
    source = '"""Doc: dataset.root."""\nraise ValueError(f"dataset.root={root}: no such folder")\n'
    assert [text for _, text in _code_strings(source) if CONFIG_KEY.search(text)] == [
        "dataset.root="
    ]


def _owners() -> set[str]:
    """The dotted name of every ``owner=`` an ArgumentError of the package is raised with."""
    owners = set()
    for path in sorted((REPO / "fusion_depth").rglob("*.py")):
        module = ".".join(path.relative_to(REPO).with_suffix("").parts)
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            for keyword in getattr(node, "keywords", []) if isinstance(node, ast.Call) else []:
                named = isinstance(keyword.value, ast.Name) and keyword.value.id != "owner"
                if keyword.arg == "owner" and named:  # not a helper passing its own on
                    owners.add(f"{module}.{keyword.value.id}")
    return owners


def test_every_owner_raised_with_has_its_keys_and_every_entry_exists() -> None:
    owners = _owners()
    assert len(owners) >= 15, owners  # the scan finds them
    assert [o for o in sorted(owners) if arguments._where(o) is None] == []
    for entry in arguments.ARGUMENT_KEYS:
        module, _, name = entry.rpartition(".")
        try:
            importlib.import_module(entry)
        except ModuleNotFoundError:
            assert hasattr(importlib.import_module(module), name), entry


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        # the reader's root is ${dataset.root}: named where the user sets it
        (["dataset=kitti"], r"^dataset\.root=/nowhere: no such folder"),
        # a value set on the reader itself keeps its own key
        (["dataset=kitti", "dataset.reader.root=/nowhere"], r"^dataset\.reader\.root=/nowhere"),
    ],
)
def test_a_command_names_the_key_where_the_argument_is_set(overrides, message, tmp_path) -> None:
    cfg = compose_config(overrides, tmp_path / "run")
    GlobalHydra.instance().clear()

    def task(cfg) -> None:
        require_root("/nowhere", "a folder")

    with pytest.raises(CommandError, match=message):
        _short_errors(task)(cfg)


def test_an_error_wrapped_by_hydras_instantiate_is_named_too(tmp_path) -> None:
    from hydra.utils import instantiate

    cfg = compose_config(["loss.w_ssim=1.0"], tmp_path / "run")
    GlobalHydra.instance().clear()

    def task(cfg) -> None:  # a schedule built by name, as the module builds it
        instantiate({"_target_": "fusion_depth.optim.schedules.schedule_class", "name": "nope"})

    with pytest.raises(CommandError, match=r"^scheduler\.name='nope': unknown schedule"):
        _short_errors(task)(cfg)


def test_it_survives_a_trip_to_another_process() -> None:
    import pickle

    from fusion_depth.models.radarnet import AssociationWeightsError

    for err in (
        ArgumentFileError("{root}=/x: no such folder", "root", owner="fusion_depth.data.kitti"),
        AssociationWeightsError(
            "{association_weights}=/x.ckpt: no such file",
            "association_weights",
            owner="fusion_depth.models.radarnet.RadarNet",
        ),
    ):
        back = pickle.loads(pickle.dumps(err))
        assert (type(back), str(back), back.arguments, back.owner) == (
            type(err),
            str(err),
            err.arguments,
            err.owner,
        )
        assert arguments.config_message(back) == arguments.config_message(err)


def test_the_message_names_each_argument_it_lists() -> None:
    err = ArgumentFileError(
        "{weights}=/x.pth: no such file; or {pretrained}=false",
        "weights",
        "pretrained",
        owner="fusion_depth.models.encoder.create_timm_model",
    )
    assert str(err) == "weights=/x.pth: no such file; or pretrained=false"
    assert isinstance(err, FileNotFoundError) and isinstance(err, ArgumentError)
    assert arguments.config_message(err) == (
        "backbone.weights=/x.pth: no such file; or backbone.pretrained=false"
    )


def test_the_line_the_command_prints_is_the_mapped_one(tmp_path) -> None:
    """What _short_errors raises is printed as it is (``_report``): the error it came from is
    not named again without the run's config."""
    from fusion_depth.config.hydra_main import user_message

    cfg = compose_config(["dataset=kitti"], tmp_path / "run")
    GlobalHydra.instance().clear()

    def task(cfg) -> None:
        require_root("/nowhere", "a folder")

    with pytest.raises(CommandError) as err:
        _short_errors(task)(cfg)
    assert user_message(err.value) == str(err.value)
    assert str(err.value).startswith("dataset.root=/nowhere")


def test_a_networks_range_and_registration_are_named_as_the_model_keys(tmp_path) -> None:
    from fusion_depth.models import DepthNet
    from fusion_depth.models.radarnet import RadarNet

    cfg = compose_config(["experiment=smoke", "model.net.min_depth=90"], tmp_path / "run")
    GlobalHydra.instance().clear()
    with pytest.raises(ArgumentError) as err:
        DepthNet("resnet18", "rgb", min_depth=90.0, max_depth=80.0)
    shown = arguments.config_message(err.value, cfg=cfg)
    assert shown.startswith("model.net.min_depth=90.0, dataset.max_depth=80.0: expected 0 <")
    with pytest.raises(ArgumentError, match="model=radarnet cannot take fusion=rgb"):
        RadarNet(fusion="rgb")  # built directly, not through create_model
