"""RelightNet at inference: the inputs of one view (paper Sec. 3.2: coarse texture, normals of frames t, t−1, t−2,
view direction, camera-space envmap) and the texture RelightNet makes of them. Training
(:mod:`gra_mi.relightnet.train`), batch relighting and the refiner's data all get a view's RelightNet render here.
"""

from __future__ import annotations

import numpy as np
import torch

from gra_mi.relightnet.model import RelightNet
from gra_mi.render.bridge import NUM_NORMAL_FRAMES, to_torch, uv_features
from gra_mi.render.relighter import Relighter, ViewRender
from gra_mi.stage.envmap import leds_to_envmap, to_camera_space


def view_inputs(
    relighter, frame: int, camera: str, intensities: np.ndarray, env_height: int, device: str = "cpu", near_lights=None, far_field=None
):
    """RelightNet's inputs for one view: (features, mask, camera-space env, shading); ``far_field`` as in
    :meth:`Relighter.render`."""
    from gra_mi.render.atlas import TexelGeometry
    from gra_mi.render.point_light import as_light_list, conditioning_of

    stage = relighter.ls.stage
    shading, geom = relighter.shade(frame, camera, intensities, near_lights, far_field)
    seq = relighter.ls.sequence
    normals = [np.array(geom.normal).T]  # frame t: already interpolated for the shading
    normals += [
        np.array(TexelGeometry.from_frame(relighter.atlas, seq.vertices[max(frame - k, 0)], seq.normals[max(frame - k, 0)]).normal).T
        for k in range(1, NUM_NORMAL_FRAMES)
    ]
    features, mask = uv_features(relighter.atlas, shading.radiance, normals, shading.view_dir, device)
    lights = intensities
    near_lights = as_light_list(near_lights)
    if near_lights:  # the paper's conditioning stands for the near-field lights in the envmap
        lights = intensities + conditioning_of(stage, relighter.ls.scene, near_lights) * stage.led_distances()[:, None] ** 2
    env = to_camera_space(leds_to_envmap(stage, lights, env_height), stage.camera(camera), supersample=1)
    return features, mask, to_torch(env, device).permute(2, 0, 1)[None].contiguous(), shading


def relightnet_texture(model: RelightNet, relighter, frame: int, camera: str, intensities: np.ndarray, near_lights=None, far_field=None):
    """Inference: RelightNet's UV texture (R, R, 3) for one view, and the one-bounce shading it started from."""
    device = next(model.parameters()).device
    features, mask, env, shading = view_inputs(
        relighter, frame, camera, intensities, model.config.env_height, str(device), near_lights, far_field
    )
    with torch.inference_mode():
        texture = model(features, env, mask)
    return texture[0].permute(1, 2, 0).cpu().numpy(), shading


def render_view(
    relighter: Relighter,
    model: RelightNet | None,
    frame: int,
    camera: str,
    intensities: np.ndarray,
    near_lights=None,
    far_field: bool | None = None,
) -> ViewRender:
    """One view at one stage: the one-bounce render (``model`` None) or RelightNet's texture of it, seen by the camera.
    ``far_field`` None: the relighter's own lighting model."""
    if model is None:
        return relighter.render(frame, camera, intensities, near_lights, far_field)
    texture, shading = relightnet_texture(model, relighter, frame, camera, intensities, near_lights, far_field)
    shading.radiance = relighter.atlas.gather(texture)
    return ViewRender(relighter.rasterize(frame, camera, texture), shading, relighter.geometry(frame))
