"""Procedural street scenes with exact depth, normals and poses (tests, training, demo).

    from rectified_colmap import synth
    scene = synth.street(np.random.default_rng(0))
    K, R, c = synth.random_view(scene, rng, 640, 480)      # R: world-from-camera, c: centre
    out = synth.render(scene, K, R, c, 640, 480, seed=scene.seed)
    out["image"], out["depth"], out["normals"]              # RGB uint8, z-depth (0 = sky)
"""

from ..training.render import Scene, Textures, random_sample, random_view, render, street

__all__ = ["Scene", "Textures", "random_sample", "random_view", "render", "street"]
