"""The deformation benchmark's variants name real EditConfig switches, all of them, from eval-edits' paper renderer."""
import dataclasses

from core.frames.edited import EditConfig
from tools.bench.deformation import VARIANTS
from tools.eval_edits import RENDERERS


def test_variants_are_edit_configs_with_every_switch_named():
    fields = {f.name for f in dataclasses.fields(EditConfig)}
    paper = set(RENDERERS["paper"])
    for name, switches in VARIANTS.items():
        assert set(switches) <= fields, (name, set(switches) - fields)
        assert paper <= set(switches), (name, paper - set(switches))
        EditConfig(**switches)  # valid values


def test_off_variant_is_the_paper_renderer_with_deform_aware_correspondence():
    off = VARIANTS["paper, deform-aware"]
    assert {k: v for k, v in off.items() if k not in ("correspondence", "f_radius_rule")} == {
        k: v for k, v in RENDERERS["paper"].items() if k != "f_radius_rule"}
    assert off["correspondence"] == "deform-aware"


def test_a_changed_variant_is_the_named_one_with_its_fields_changed():
    from tools.bench.regions import parse_variant

    base = next(v for v in VARIANTS if "squash grid" in v)
    name, fields = parse_variant(f"{base}:squash_grid_finest=0.125,grid_filter=1", VARIANTS)
    assert name == f"{base}:squash_grid_finest=0.125,grid_filter=1"
    assert fields == {**VARIANTS[base], "squash_grid_finest": 0.125, "grid_filter": 1}
    EditConfig(**fields)


def test_the_variant_named_the_default_renderer_is_editconfigs_defaults():
    """The variant the docs time as "the default renderer" sets every EditConfig field it names to its default."""
    name = next(v for v in VARIANTS if v.endswith("(the default renderer)"))
    assert all(getattr(EditConfig, f) == x for f, x in VARIANTS[name].items()), name
