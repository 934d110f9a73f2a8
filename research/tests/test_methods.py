"""rectified_colmap_research.evaluation.methods: the rows of every evaluation table."""

import pytest
from rectified_colmap_research.evaluation.methods import (
    depth_model_of,
    is_plain,
    method_conf,
    parse_variants,
    plain_budget,
)

from rectified_colmap.config import DEFAULT_DEPTH_MODEL, ExtractConf, confs


def test_plain_sift_is_exactly_the_sift_conf_with_its_budget():
    assert method_conf("sift") == confs["sift"]
    c = ExtractConf.from_dict(method_conf("sift@1024", base={"vp": {"line_hypotheses": 2}}))
    assert c.sift.max_num_features == 1024 and not c.sift.coarse_first
    assert c.planes.min_area_frac > 1 and c.vp.line_hypotheses == 0  # base ignored for plain
    assert is_plain("sift@7") and not is_plain("sifty") and plain_budget("sift") is None
    with pytest.raises(ValueError, match="sift@N"):
        plain_budget("sift@x")


def test_rectified_methods_layer_base_own_and_budget():
    variants = parse_variants(['a={"rectify": {"tilt_steps": 0}}', "fast=rectsift-fast"])
    assert variants == {"a": {"rectify": {"tilt_steps": 0}}, "fast": confs["rectsift-fast"]}
    variants["fast"]["sift"]["max_num_features"] = 1  # a copy: the named conf is untouched
    assert confs["rectsift-fast"]["sift"]["max_num_features"] == 4096
    base = {"rectify": {"tilt_steps": 2, "border": 3}}
    conf = method_conf("a", variants, base, max_num_features=2048)
    assert conf == {"rectify": {"tilt_steps": 0, "border": 3}, "sift": {"max_num_features": 2048}}
    assert method_conf("rectsift") == {} and method_conf("rectsift-fast") == confs["rectsift-fast"]
    assert base == {"rectify": {"tilt_steps": 2, "border": 3}}  # inputs unchanged
    with pytest.raises(ValueError, match="not a method"):
        method_conf("nope")


@pytest.mark.parametrize(
    "spec", ["noequals", "=x", "sift={}", "sift@2={}", "a=[1]", "a={bad json", "rectsift={}"]
)
def test_bad_variants_fail_in_one_line(spec):
    with pytest.raises(ValueError) as e:
        parse_variants([spec], taken=("rectsift",))
    assert "\n" not in str(e.value) and "--variant" in str(e.value)


def test_depth_model_of():
    assert depth_model_of("sift") is None and depth_model_of("sift@5", "x.onnx") is None
    assert depth_model_of("rectsift") == DEFAULT_DEPTH_MODEL
    assert depth_model_of("v", "x.onnx") == "x.onnx"


def test_variant_argument_repeats_and_parses():
    import argparse

    from rectified_colmap_research.evaluation.methods import add_variant_argument

    p = argparse.ArgumentParser()
    add_variant_argument(p, on_top_of="--rect_conf")
    args = p.parse_args(["--variant", "a={}", "--variant", "fast=rectsift-fast"])
    assert parse_variants(args.variant) == {"a": {}, "fast": confs["rectsift-fast"]}
    assert p.parse_args([]).variant == []
    assert "on top of --rect_conf" in p.format_help().replace("\n", " ").replace("  ", " ")
