"""Register: scans with their cameras moved rigidly onto each other when that makes them consistent."""

from __future__ import annotations

import logging

import numpy as np

from o3drbf.options import RegistrationOptions
from o3drbf.pointset import PointSet

__all__ = ["register_scans"]

log = logging.getLogger("o3drbf")


def register_scans(data: PointSet, options: RegistrationOptions = RegistrationOptions(), *, seed: int = 0):
    """Move each scan rigidly onto the others, with its camera, when that makes them consistent.

    Parameters
    ----------
    data : PointSet
        Needs cameras and ``point_camera`` (the scan of each point); without
        them nothing is done.
    options : RegistrationOptions
    seed : int

    Returns
    -------
    PointSet
        The moved points and cameras (the same object when nothing moved).
    Registration or None
        What :func:`o3drbf.prep.registration.refine_registration` found
        (None when it did not run: ``register="none"``, no cameras or no
        ``point_camera``).

    Examples
    --------
    >>> import numpy as np
    >>> from o3drbf.synthetic.shapes import Sphere
    >>> points, normals = Sphere(1.0).sample(600, noise=0.002, seed=0)
    >>> from o3drbf import PointSet
    >>> data = PointSet.create(points, normals)
    >>> from o3drbf import register_scans
    >>> moved, registration = register_scans(data)  # no cameras: nothing to register
    >>> moved is data, registration is None
    (True, True)
    """
    options.validate()
    if options.method == "none" or data.cameras is None or data.point_camera is None:
        return data, None
    from dataclasses import replace

    from o3drbf.prep.registration import apply_transforms, refine_registration

    toward = np.zeros_like(data.points)
    for k, camera in enumerate(data.cameras):
        sel = data.point_camera == k
        if sel.any():
            toward[sel] = camera.toward(data.points[sel])[0]
    reg = refine_registration(data.points, data.point_camera, len(data.cameras), toward=toward, min_gain=options.min_gain, seed=seed)
    log.info("registration: %s", reg.reason)
    if not reg.applied:
        return data, reg
    cameras = [camera.moved(T) for camera, T in zip(data.cameras, reg.transforms)]
    normals = None if data.normals is None else apply_transforms(data.normals, data.point_camera, reg.transforms, vectors=True)
    moved = replace(data, points=apply_transforms(data.points, data.point_camera, reg.transforms), normals=normals,
                    cameras=cameras, _cache={})
    return moved, reg
