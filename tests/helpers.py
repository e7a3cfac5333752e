"""Shared test helpers: random rigs and points with known geometry."""

import jax.numpy as jnp
import numpy as np

import jaxstereo as js


def random_camera(rng, center, target, dist_scale=0.0, image_size=(1200, 900), focal=(900.0, 1400.0)):
    f = rng.uniform(*focal)
    pose = js.Pose.look_at(center, target)
    dist = np.zeros(5)
    if dist_scale:
        dist = dist_scale * np.array(
            [rng.uniform(-0.2, 0.2), rng.uniform(-0.05, 0.05), rng.uniform(-2e-3, 2e-3), rng.uniform(-2e-3, 2e-3),
             rng.uniform(-0.02, 0.02)]
        )
    w, h = image_size
    return js.Camera(f, f * rng.uniform(0.98, 1.02), w / 2 + rng.uniform(-20, 20), h / 2 + rng.uniform(-20, 20),
                     dist, pose, image_size)


def random_refraction_case(rng, max_incidence_deg=45.0, max_tilt_deg=5.0, n=200):
    """A random camera above a tilted interface and points under it seen at incidence <= the given maximum.

    Points are made by tracing rays forward with the vector Snell law (an independent path from the
    forward-projection solver under test).
    """
    tilt = np.deg2rad(rng.uniform(-max_tilt_deg, max_tilt_deg, 2))
    level = rng.uniform(-0.2, 0.4)
    interface = js.Interface.from_tilt(level, tilt[0], tilt[1], n_water=rng.uniform(1.30, 1.36))
    normal = np.asarray(interface.normal)
    height = rng.uniform(0.5, 3.0)
    foot = np.array([rng.uniform(-1, 1), rng.uniform(-1, 1), 0.0])
    foot = foot + (level - foot @ normal) * normal
    center = foot + height * normal
    # Unit directions around -normal at the requested incidences.
    inc = np.deg2rad(rng.uniform(0.0, max_incidence_deg, n))
    az = rng.uniform(0, 2 * np.pi, n)
    e1 = np.cross(normal, [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(normal, e1)
    d = (np.sin(inc) * np.cos(az))[:, None] * e1 + (np.sin(inc) * np.sin(az))[:, None] * e2 - np.cos(inc)[:, None] * normal
    hit = center + (height / np.cos(inc))[:, None] * d
    refracted, ok = js.refract_directions(jnp.asarray(d), interface.normal, interface.n_air, interface.n_water)
    depth = rng.uniform(0.01, 1.0, n)
    refracted = np.asarray(refracted)
    points = hit + (depth / -(refracted @ normal))[:, None] * refracted
    # The optical axis within 10 degrees of the normal, so that 45 degrees of incidence stays within a
    # wide-angle lens' field where its distortion is invertible.
    target = foot + height * np.tan(np.deg2rad(10.0)) * rng.uniform(-0.7, 0.7) * (e1 + e2)
    camera = random_camera(rng, center, target, dist_scale=0.3)
    return camera, interface, jnp.asarray(points), hit
