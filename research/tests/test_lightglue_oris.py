"""rectified_colmap_research.evaluation.lightglue: orientations in radians for LightGlue
(against pycolmap's SIFT angles: test_hloc_integration)."""

import numpy as np
import pytest

from rectified_colmap_research.evaluation.lightglue import (
    convert_oris_for_lightglue,
    oris_for_lightglue,
)


def test_oris_for_lightglue(tmp_path):
    import h5py

    assert oris_for_lightglue(np.array([180.0])).dtype == np.float32
    with h5py.File(tmp_path / "a.h5", "w") as f:
        g = f.create_group("db/x.jpg")
        g["keypoints"] = np.zeros((3, 2), np.float32)
        g["oris"] = np.array([0, 90, -180], np.float32)
        g["scales"] = np.ones(3, np.float32)
    assert convert_oris_for_lightglue(tmp_path / "a.h5", tmp_path / "b.h5") == 1
    with h5py.File(tmp_path / "b.h5") as f:
        np.testing.assert_allclose(f["db/x.jpg/oris"][()], [0, np.pi / 2, -np.pi], atol=1e-6)
        assert f["db/x.jpg/oris"].attrs["oris_unit"] == "rad"
        np.testing.assert_array_equal(f["db/x.jpg/scales"][()], 1)
    with pytest.raises(ValueError, match="new file"):
        convert_oris_for_lightglue(tmp_path / "a.h5", tmp_path / "a.h5")
    with pytest.raises(ValueError, match="already in radians"):
        convert_oris_for_lightglue(tmp_path / "b.h5", tmp_path / "c.h5")
