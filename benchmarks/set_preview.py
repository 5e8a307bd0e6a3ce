"""How close `export --set`'s preview material comes to the BSDF it stands for: a ball of each BSDF under a sky and a
softbox (`near_field_cases.ball_scene`), rendered by Mitsuba's `path` with the BSDF itself (the truth) and with its
preview as a DCC tool would render it (Mitsuba's `principled` with the preview's base colour, roughness and metallic,
its specular set to the preview's F0: 0.04 from ior 1.5, UsdPreviewSurface's and glTF's default; 0 from ior 1, a
BSDF without a glossy lobe). Mitsuba's principled has Burley's diffuse, whose retro-reflection UsdPreviewSurface's and
glTF's Lambertian diffuse have not: on a diffuse ball that difference is the preview's whole error.

Beside it, two simpler stand-ins: the diffuse BSDF of the preview's base colour (what an export without roughness and
metal would give, and what `from-scene` writes for a BSDF it cannot carry), and a constant guess (grey diffuse 0.5).
Error: the mean relative error over the ball's pixels and the bias of the mean (`near_field_cases.image_error`);
*noise*: the truth rendered again with another seed.

    .venv/bin/python benchmarks/set_preview.py [--spp 1024] [--write docs/results/set-preview.md]
"""

from __future__ import annotations

from gra_mi.apps.harness import BenchmarkRun, run_benchmark, table_page

SIZE = 96
BSDFS = {  # a name → the Mitsuba BSDF a user's set shape might hold
    "diffuse 0.5": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.5, 0.5, 0.5]}},
    "diffuse, checkerboard texture": {"type": "diffuse", "reflectance": {"type": "checkerboard", "color0": {"type": "rgb", "value": 0.1},
                                                                          "color1": {"type": "rgb", "value": 0.8}}},
    "roughplastic (0.8, 0.2, 0.1), α 0.1": {"type": "roughplastic", "diffuse_reflectance": {"type": "rgb", "value": [0.8, 0.2, 0.1]}},
    "plastic, smooth coat": {"type": "plastic", "diffuse_reflectance": {"type": "rgb", "value": [0.2, 0.4, 0.7]}},
    "principled (0.2, 0.4, 0.6), roughness 0.6": {"type": "principled", "base_color": {"type": "rgb", "value": [0.2, 0.4, 0.6]}, "roughness": 0.6},
    "roughconductor Al, α 0.25": {"type": "roughconductor", "material": "Al", "alpha": 0.25},
    "roughconductor Au, α 0.1": {"type": "roughconductor", "material": "Au", "alpha": 0.1},
    "conductor (a mirror)": {"type": "conductor"},
}  # fmt: skip


def _render(scene, spp: int, seed: int):
    import mitsuba as mi
    import numpy as np

    integrator = mi.load_dict({"type": "path", "max_depth": 2})
    return np.array(mi.render(scene, integrator=integrator, spp=spp, seed=seed), np.float64)


def _ball(bsdf: dict):
    from gra_mi.render.near_field_cases import ball_scene

    return ball_scene(bsdf, SIZE)


def _row(name: str, bsdf: dict, spp: int) -> tuple:
    from gra_mi.apps.set_export import preview_material
    from gra_mi.render.near_field_cases import image_error

    scene = _ball(bsdf)
    said = preview_material(scene, scene.shapes()[0])
    f0 = ((said.ior - 1) / (said.ior + 1)) ** 2  # (principled's specular s gives F0 = 0.08 s)
    preview = {"type": "principled", "base_color": {"type": "rgb", "value": list(said.base_color)},
               "roughness": max(said.roughness, 1e-3), "metallic": said.metallic, "specular": f0 / 0.08}  # fmt: skip
    diffuse = {"type": "diffuse", "reflectance": {"type": "rgb", "value": list(said.base_color)}}
    grey = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.5, 0.5, 0.5]}}
    truth = _render(scene, spp, 0)
    errors = [image_error(_render(_ball(stand_in), spp, 1), truth) for stand_in in (preview, diffuse, grey)]
    noise = image_error(_render(scene, spp, 1), truth)
    cells = [f"{error:.1%} / {bias:+.1%}" for error, bias in [*errors, noise]]
    return (name, said.said(), *cells)


def measure(run: BenchmarkRun) -> str:
    rows = [_row(name, bsdf, run.args.spp) for name, bsdf in BSDFS.items()]
    notes = [
        f"A ball of radius 0.3 m, {SIZE}×{SIZE}, `path` (max_depth 2: the ball's direct light, its own reflections "
        f"included) at {run.args.spp} spp for every render. Each cell: mean relative error / bias of the mean against the "
        "truth.",
        "What the preview leaves out shows by kind: a texture becomes its mean colour (the checkerboard's error is its "
        "pattern); a coat and a metal keep their highlight, which the diffuse stand-ins lose (8–15 % error, a coat's light −7 %)"
        "; a principled BSDF is its own preview; a mirror becomes principled's sharpest lobe. On a diffuse ball the "
        "preview's error is principled's Burley diffuse (its retro-reflection), not the preview: UsdPreviewSurface's and "
        "glTF's diffuse is Lambert's, the diffuse BSDF's own. A metal's base colour (F0) is the one for which glTF's GGX "
        "metal of its roughness reflects as much light as it does: its albedo itself, which holds its microfacets' "
        "masking already, rendered 6 % dark here. Mitsuba's roughconductor is Beckmann by default, whose short tails "
        "shadow less than GGX's at one α: aluminium at α 0.25 reflects more than any GGX metal of roughness 0.5, and "
        "its base colour is white (clipped at 1).",
    ]
    columns = ("BSDF", "preview", "preview (principled)", "diffuse of the base colour", "grey diffuse 0.5", "noise")
    return table_page("The set's preview materials against the BSDFs they stand for", "set_preview.py",
                      run.stamp(f"a ball, {SIZE}×{SIZE}"), rows, notes, columns)  # fmt: skip


if __name__ == "__main__":
    run_benchmark(
        __doc__, measure, arguments=lambda p: p.add_argument("--spp", type=int, default=1024, help="Samples per pixel of every render.")
    )
