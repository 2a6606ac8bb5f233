"""How ``report`` names a row's setting in its Markdown tables and figures: short labels
(fusion_depth.report.groups.short_settings), whole millimetres (Preset.decimals)."""

from __future__ import annotations

from fusion_depth.report.groups import Preset, settings_note, short_settings

ALIGNMENT = "alignment.ransac_iterations={n} alignment.space=inverse alignment.target={target}"
RANSAC = "alignment.ransac_iterations=100 alignment.ransac_threshold=0.1 alignment.space=inverse"
WEIGHTS = "prior.weights=multirun/study/stand-in/checkpoints/epoch021-loss0.0955.ckpt"


def test_what_every_row_that_sets_a_key_shares_is_named_once() -> None:
    """The prior study's settings: the weights every prior row shares and the fit's space are
    left out (and returned, for the line under the table); what tells rows apart stays, its
    dotted keys cut to their last part."""
    settings = [
        "",
        f"{WEIGHTS} prior=checkpoint",
        f"{WEIGHTS} prior=checkpoint prior=none",
        ALIGNMENT.format(n=0, target="sparse"),
        f"{RANSAC} alignment.target=sparse",
    ]
    labels, left_out = short_settings(settings)
    assert [labels[s] for s in settings] == [
        "",
        "prior=checkpoint",
        "prior=checkpoint prior=none",
        "ransac_iterations=0",
        "ransac_iterations=100",
    ]
    assert left_out == (
        "alignment.ransac_threshold=0.1",
        "alignment.space=inverse",
        "alignment.target=sparse",
        WEIGHTS,
    )
    note = settings_note([{"setting_shared": left_out}])
    assert note.startswith("\n\nLeft out of Setting") and f"`{WEIGHTS}`" in note


def test_a_shared_override_stays_where_rows_would_look_alike() -> None:
    """Left out, ``prior=checkpoint`` would make the prior's row read as the baseline's (both
    empty): the shortest such override is kept again; the weights still go."""
    settings = ["", f"{WEIGHTS} prior=checkpoint"]
    labels, left_out = short_settings(settings)
    assert labels == {"": "", settings[1]: "prior=checkpoint"}
    assert left_out == (WEIGHTS,)
    # One run with a setting and one without: the setting is all that tells them apart.
    labels, left_out = short_settings(["optimizer.lr=0.001", ""])
    assert labels == {"optimizer.lr=0.001": "lr=0.001", "": ""} and left_out == ()


def test_a_dotted_key_is_cut_only_where_its_last_part_names_it() -> None:
    """``a.x`` and ``b.x`` keep their full names (one ``x`` would be either), even where one
    of them is left out; ``+`` and ``~`` stay in front."""
    labels, left_out = short_settings(["a.x=1 b.x=2", "a.x=1 b.x=3"])
    assert labels == {"a.x=1 b.x=2": "b.x=2", "a.x=1 b.x=3": "b.x=3"} and left_out == ("a.x=1",)
    labels, _ = short_settings(["+model.lr=1", "+model.lr=2"])
    assert labels == {"+model.lr=1": "+lr=1", "+model.lr=2": "+lr=2"}


def test_lengths_in_millimetres_print_whole() -> None:
    """RadarNet's protocol prints MAE and RMSE in mm: to the millimetre, not to a thousandth
    of one; metres, ratios and 1/km keep three decimals."""
    radarnet = Preset(name="radarnet", metrics=("mae", "rmse", "imae", "irmse"), units="mm")
    assert [radarnet.decimals(m) for m in radarnet.metrics] == [0, 0, 3, 3]
    assert {Preset().decimals(m) for m in Preset().metrics} == {3}
