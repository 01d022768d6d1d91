"""registration.run.config: the ``paper`` preset holds the paper's numbers (section by section), every
setting of every stage is documented in its dataclass and read by the code, configurations
survive the JSON round trip of result.json, and bad names are one-line errors."""

from __future__ import annotations

import ast
import dataclasses
import inspect
import json
import re
import typing
from pathlib import Path

import pytest

from registration.matching import TemplateConfig
from registration.run import PRESETS, PipelineConfig, config_from_dict, config_to_dict, get_preset
from registration.run.config import _dataclass_in

REPO = Path(__file__).resolve().parents[2]


def test_paper_preset_holds_the_papers_numbers():
    """Loveland & Rosten, section by section (the values the paper states)."""
    p = get_preset("paper")
    # The dataclass defaults, but for the template matching (whose defaults carry the checks
    # beyond the paper that every other preset uses).
    d = PipelineConfig()
    as_defaults = dataclasses.replace(
        p,
        fine=dataclasses.replace(p.fine, template=d.fine.template),
        intra=dataclasses.replace(p.intra, template=d.intra.template),
    )
    assert as_defaults == d
    assert p.fine.template == p.intra.template == TemplateConfig.paper()
    # 4.3.1: grey, 1/4 scale, one seed, SIFT, RANSAC (4 points, 5 px, 1000 iterations) with
    # Nelder-Mead to a projective; nothing beyond the paper.
    c = p.coarse
    assert c.scale == 0.25 and c.min_side_px == 0
    assert (c.ransac.sample_size, c.ransac.threshold_px, c.ransac.max_iterations) == (4, 5.0, 1000)
    assert c.ransac.refine == "nelder-mead"
    assert c.models == ("projective",)
    assert not c.guided and c.refine_rounds == 0 and not c.match_base_scale
    assert c.correlation.rounds == ()
    # 4.3.2: degree-2 polyprojective (17 coefficients), 75x75 templates every 50 px, 20x20
    # search, dithered NCC, REQCON dropping the worst 5 % until the mean error < 2 px, Nelder-Mead.
    f = p.fine
    assert f.degree == 2 and not f.check_support
    t = f.template
    assert (t.template_px, t.spacing_px, t.search_px) == (75, 50, 20)
    assert t.dither_iterations >= 1 and t.edge_template_px == 0
    r = f.reqcon
    assert (r.drop_fraction, r.target_mean_error_px, r.optimizer, r.stop) == (
        0.05, 2.0, "nelder-mead", "mean",
    )  # fmt: skip
    # 4.4: gridded SIFT, 50x50 windows every 100 px, the joint list decimated by 3, the previous
    # frame beside the mid base image, REQCON as above.
    i = p.intra
    assert i.control_points == "gridded_sift" and i.use_previous_frame
    g = i.gridded
    assert (g.window_px, g.spacing_px, g.decimate) == (50, 100, 3)
    assert i.coarse_nfeatures == 0 and i.reqcon == r
    # 5: SIFT in 200x200 neighbourhoods 200 px apart, one REQCON consensus vector each.
    loc = p.local
    assert (loc.method, loc.cell_px, loc.spacing_px, loc.cell_model) == (
        "sift", 200, 200, "translation",
    )  # fmt: skip
    # 3 and 4.2: matching in the corrected frame; no field of the reference frame's own.
    assert p.match_in == "corrected" and p.run_local and p.reference_local is None


def test_paper_preset_correlates_templates_directly_as_the_paper():
    """Paper 4.3.2: templates correlated directly in base pixels around the coarse prediction,
    every peak left to REQCON (TemplateConfig.paper())."""
    assert get_preset("paper").fine.template == TemplateConfig.paper()


def test_default_preset_differs_from_the_paper_and_is_valid():
    paper, default = get_preset("paper"), get_preset("default")
    assert default != paper
    # The stages the README's "Presets" section says the default preset changes.
    assert default.coarse.ransac.refine == "lm" and default.fine.reqcon.optimizer == "lm"
    assert default.fine.reqcon.stop == "outliers"
    assert default.intra.control_points == "template" and default.local.method == "flow"
    # The fast preset: the default one with control points from the frame's flow, and no
    # sequence adjustment (the paper has none either).
    fast = get_preset("fast")
    assert fast.intra.control_points == "flow"
    assert default.adjust is not None and fast.adjust is None and paper.adjust is None
    assert default == dataclasses.replace(
        fast,
        intra=dataclasses.replace(fast.intra, control_points="template"),
        adjust=default.adjust,
    )
    assert default.match_in == "raw" and default.reference_local is not None
    assert default.coarse.correlation.rounds and default.coarse.guided


def _config_classes() -> list[type]:
    out: list[type] = []

    def walk(cls):
        if cls in out:
            return
        out.append(cls)
        hints = typing.get_type_hints(cls)
        for f in dataclasses.fields(cls):
            sub = _dataclass_in(hints[f.name])
            if sub is not None:
                walk(sub)

    walk(PipelineConfig)
    return out


def _documented(cls) -> set[str]:
    """Names an ``Attributes:``-style docstring describes (``name:``, ``a, b:``,
    ``name (unit):`` at the start of a line)."""
    names = set()
    for line in (inspect.getdoc(cls) or "").splitlines():
        m = re.match(r"^\s{0,8}([A-Za-z_]\w*(?:\s*,\s*[A-Za-z_]\w*)*)\s*(?:\([^)]*\))?:", line)
        if m:
            names |= {n.strip() for n in m.group(1).split(",")}
    return names


def _attributes_read() -> set[str]:
    """Every attribute name the library and the app read somewhere (``x.name`` in code)."""
    reads = set()
    for folder in ("registration", "app"):
        for path in (REPO / folder).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text(), str(path))):
                if isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Load):
                    reads.add(node.attr)
    return reads


def test_every_setting_is_documented_and_read():
    classes = _config_classes()
    assert len(classes) >= 10  # every stage's config is reachable from PipelineConfig
    reads = _attributes_read()
    undocumented, unread = [], []
    for cls in classes:
        doc = _documented(cls)
        for f in dataclasses.fields(cls):
            if f.name not in doc:
                undocumented.append(f"{cls.__name__}.{f.name}")
            if f.name not in reads:
                unread.append(f"{cls.__name__}.{f.name}")
    assert not undocumented, f"settings missing from their class docstring: {undocumented}"
    assert not unread, f"settings no code reads: {unread}"


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_presets_survive_the_json_round_trip_of_result_json(name):
    config = get_preset(name)
    data = json.loads(json.dumps(config_to_dict(config)))
    assert config_from_dict(data) == config
    # Missing keys take the defaults (a result written before a setting existed).
    data["coarse"].pop("scale")
    assert config_from_dict(data).coarse.scale == PipelineConfig().coarse.scale


def test_bad_names_are_one_line_errors():
    with pytest.raises(
        ValueError, match="unknown preset 'quick'; choose from paper, default, fast"
    ):
        get_preset("quick")
    with pytest.raises(ValueError, match=r"unknown key config\.fine\.degre \(known:"):
        config_from_dict({"fine": {"degre": 3}})
    with pytest.raises(ValueError, match="config.coarse must be an object, got list"):
        config_from_dict({"coarse": [1]}, PipelineConfig)
    with pytest.raises(ValueError, match="models"):
        dataclasses.replace(PipelineConfig().coarse, models=("homography",))
    intra = PipelineConfig().intra
    with pytest.raises(ValueError, match="control_points must be 'gridded_sift', 'template' or"):
        dataclasses.replace(intra, control_points="sift")
    with pytest.raises(ValueError, match="flow control points need template.warp_reference=True"):
        dataclasses.replace(
            intra,
            control_points="flow",
            template=dataclasses.replace(intra.template, warp_reference=False),
        )
    with pytest.raises(ValueError, match="flow_point_spacing_px must be >= 1, got 0"):
        dataclasses.replace(intra, flow_point_spacing_px=0)


def test_a_result_of_an_earlier_release_with_pooled_fields_says_so_in_one_line():
    data = config_to_dict(get_preset("default"))
    data["adjust"].pop("fields")
    data["adjust"].update(field_radius=5, field_baseline_px=5.0, field_support=1.0)
    with pytest.raises(ValueError, match=r"^config\.adjust\.field_baseline_px: made by an earlier"):
        config_from_dict(data)
