"""Our databases through COLMAP 4's mappers (pycolmap 4.x): the global mapper (GLOMAP,
merged into COLMAP 4: ``pycolmap.global_mapping``, ``colmap global_mapper``) maps a small
real scene from a database extracted by ``extract`` (default conf and network), as the
incremental one does. Skipped without the real-pool data."""

from itertools import combinations
from pathlib import Path

import numpy as np
import pycolmap
import pytest

from rectified_colmap.extraction import extract
from rectified_colmap.geometry import rotation_angle_deg
from rectified_colmap.io.colmap_db import ColmapDatabase

SCENE = Path(__file__).resolve().parents[3] / "shared" / "data" / "real-pool" / "sceaux-castle"
NAMES = [f"100_{i}.jpg" for i in range(7100, 7105)]
"""Five consecutive photos around the castle (1024x769, EXIF focal length)."""

pytestmark = pytest.mark.skipif(
    not (SCENE / "images").is_dir() or not (SCENE / "colmap_sparse").is_dir(),
    reason=f"real-pool data not found ({SCENE})",
)


@pytest.fixture(scope="module")
def matched(tmp_path_factory):
    """The five photos extracted into a new database and matched exhaustively."""
    db = tmp_path_factory.mktemp("sceaux") / "db.db"
    summary = extract(
        SCENE / "images", database=db, reader={"image_list": NAMES}, run={"progress": False}
    )
    assert summary.ok and len(summary.done) == len(NAMES), summary.report()
    opts = pycolmap.FeatureMatchingOptions()
    opts.num_threads = 2
    pycolmap.match_exhaustive(db, matching_options=opts, device=pycolmap.Device.cpu)
    return db


def _map(mapper: str, db: Path, out: Path) -> pycolmap.Reconstruction:
    if mapper == "global":
        opts = pycolmap.GlobalPipelineOptions()
        opts.mapper.global_positioning.use_gpu = False
        opts.mapper.bundle_adjustment.ceres.use_gpu = False
        run = pycolmap.global_mapping
    else:
        opts = pycolmap.IncrementalPipelineOptions()
        opts.min_model_size = 3
        run = pycolmap.incremental_mapping
    opts.num_threads, opts.random_seed = 1, 0
    out.mkdir()
    models = run(db, SCENE / "images", out, options=opts)
    assert models, f"{mapper} mapper: no model"
    return max(models.values(), key=lambda r: r.num_reg_images())


def _relative_rotation_errors(rec, ref) -> np.ndarray:
    """Degrees between the model's and the reference's relative rotations of every pair of
    images both registered."""
    ref_by_name = {im.name: im for im in ref.images.values()}
    ims = [im for im in rec.images.values() if im.has_pose and im.name in ref_by_name]

    def rot(im):
        return im.cam_from_world().rotation.matrix()

    return np.array(
        [
            rotation_angle_deg(
                (rot(b) @ rot(a).T).T @ rot(ref_by_name[b.name]) @ rot(ref_by_name[a.name]).T
            )
            for a, b in combinations(ims, 2)
        ]
    )


def test_cameras_claim_a_prior_focal_length_where_exif_gives_one(matched):
    """The global mapper needs focal-length priors (it warns below half of the cameras);
    EXIF's are priors, as in COLMAP's own extractor."""
    with ColmapDatabase(matched) as db:
        cams = [db.get_camera(i) for i in db.camera_ids()]
    assert len(cams) == len(NAMES) and all(c.has_prior_focal_length for c in cams)


def test_global_mapper_registers_every_image_as_the_incremental_one(matched, tmp_path):
    """pycolmap.global_mapping on our database: every image registered (at least as many
    as the incremental mapper), relative rotations within a degree of the scene's own SfM
    model (the real-pool's colmap_sparse, plain SIFT on all 11 photos)."""
    ref = pycolmap.Reconstruction(SCENE / "colmap_sparse")
    glob = _map("global", matched, tmp_path / "global")
    incremental = _map("incremental", matched, tmp_path / "incremental")
    assert glob.num_reg_images() == len(NAMES) >= incremental.num_reg_images()
    assert glob.num_points3D() > 1000
    errs = _relative_rotation_errors(glob, ref)
    assert len(errs) == len(NAMES) * (len(NAMES) - 1) // 2
    print(
        f"global {glob.num_reg_images()} images, {glob.num_points3D()} points, incremental "
        f"{incremental.num_reg_images()}, {incremental.num_points3D()}; rotation errors {errs}"
    )
    assert np.median(errs) < 1.0, errs
