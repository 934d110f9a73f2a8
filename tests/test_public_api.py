"""The public API of rectified_colmap (its __init__): the names promised to users, each
resolving to the object its module defines."""

import subprocess
import sys

import rectified_colmap

PUBLIC = [
    "extract",
    "extract_image",
    "ReaderConf",
    "DepthInputConf",
    "RunConf",
    "Sift",
    "ImageResult",
    "Features",
    "DepthMap",
    "ExtractConf",
    "NormalConf",
    "PlaneConf",
    "RectifyConf",
    "SiftConf",
    "DedupConf",
    "VpConf",
    "confs",
    "merge_conf",
]


def test_all_is_pinned():
    """A change of the public surface is a decision: update this list and docs/usage.md."""
    assert rectified_colmap.__all__ == PUBLIC


def test_every_public_name_is_its_modules_object():
    from rectified_colmap import config, depth, features, pipeline, sift
    from rectified_colmap import extraction as extract_pkg

    expected = {
        "extract": extract_pkg.extract,
        "extract_image": pipeline.extract_image,
        "ImageResult": pipeline.ImageResult,
        "Features": features.Features,
        "Sift": sift.Sift,
        "DepthMap": depth.DepthMap,
        "confs": config.confs,
        "merge_conf": config.merge_conf,
    }
    for name in PUBLIC:
        obj = getattr(rectified_colmap, name)
        assert obj is expected.get(name, getattr(config, name, None)), name
    assert set(PUBLIC) <= set(dir(rectified_colmap))


def test_star_import_and_unknown_names():
    ns = {}
    exec("from rectified_colmap import *", ns)
    assert set(PUBLIC) <= set(ns)
    try:
        rectified_colmap.no_such_name  # noqa: B018
    except AttributeError as e:
        assert "no_such_name" in str(e)
    else:
        raise AssertionError("unknown names must raise AttributeError")


def test_extract_is_the_function_and_its_subpackage_is_importable_by_name():
    """`rectified_colmap.extract` is the function, and importing the extraction subpackage
    (named apart from it, so nothing shadows anything) does not change that."""
    code = (
        "import rectified_colmap.extraction.run as run, rectified_colmap.extraction as ex\n"
        "import rectified_colmap\n"
        "print(type(rectified_colmap.extract).__name__, type(ex).__name__, run.__name__)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.stdout.split() == ["function", "module", "rectified_colmap.extraction.run"], (
        out.stderr
    )
