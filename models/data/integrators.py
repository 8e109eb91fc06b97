"""Mitsuba integrators the renderer adds: ambient occlusion (`mcd_ao`).

Mitsuba 3 ships no AO integrator. `mcd_ao` traces the camera ray, then one cosine-distributed ray per
sample from the first hit over the hemisphere facing the viewer, and returns 1 when that ray travels
`distance` scene units unoccluded, else 0; its pixel mean over many samples is the cosine-weighted
ambient occlusion in [0, 1]. Camera rays that hit nothing return 1 (nothing occludes them).

Python integrator classes derive from the variant's `SamplingIntegrator`, so `register` defines and
registers one per variant, after `mi.set_variant` (see variant.load_mitsuba). Importing this module does
not import mitsuba.
"""

from __future__ import annotations

AO_INTEGRATOR = "mcd_ao"
_registered: set[str] = set()


def register() -> None:
    """Register `mcd_ao` for the active variant (idempotent)."""
    import mitsuba as mi

    variant = mi.variant()
    if variant in _registered:
        return
    mi.register_integrator(AO_INTEGRATOR, _ao_class())
    _registered.add(variant)


def _ao_class() -> type:
    import drjit as dr
    import mitsuba as mi

    class AmbientOcclusion(mi.SamplingIntegrator):
        """Binary visibility of one cosine-sampled ray per sample; `distance` property in scene units."""

        def __init__(self, props):
            super().__init__(props)
            self.distance = float(props.get("distance", 1.0))

        def sample(self, scene, sampler, ray, medium=None, active=True):
            si = scene.ray_intersect(ray, active)
            hit = si.is_valid()
            local = mi.warp.square_to_cosine_hemisphere(sampler.next_2d())
            direction = si.sh_frame.to_world(local)
            # The hemisphere on the side the camera sees (back faces of open shapes are visible too).
            facing_away = dr.dot(si.sh_frame.n, -ray.d) < 0.0
            direction = dr.select(facing_away, -direction, direction)
            probe = si.spawn_ray(direction)
            probe.maxt = self.distance
            occluded = scene.ray_test(probe, hit)
            value = dr.select(hit & occluded, 0.0, 1.0)
            return mi.Spectrum(value), True, []

        def aov_names(self):
            return []

        def to_string(self):
            return f"AmbientOcclusion[distance={self.distance}]"

    return AmbientOcclusion
