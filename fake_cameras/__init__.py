"""A simulated capture rig that renders real images of animated synthetic creatures, with ground truth.

Importing the package registers the ``fake`` camera driver (:mod:`fake_cameras.device`)
with :func:`stage.drivers.registry.register_driver`; the other modules are imported directly.

Modules:

``fake_cameras.dome``
    :func:`make_dome` - the true calibration of N cameras around the volume.
``fake_cameras.creatures``
    :func:`make_creature` - starfish, quadruped, biped: tapered capsules on a
    kinematic tree; ``Creature.pose(t) -> Pose`` with tips, limb axes and an exact SDF.
``fake_cameras.render``
    :func:`render_view` - ray casting through the distorted camera model in a
    green studio (shading, uneven light, floor shadows, spill, noise, depth).
``fake_cameras.mesh_render``
    :func:`render_mesh_views` - the same studio and image formation for a triangle mesh
    (Embree ray casting), any cameras of a calibration.
``fake_cameras.boards``
    :func:`render_board_views` - chessboard / ChArUco boards waved through the volume.
``fake_cameras.take``
    :func:`simulate_take` - a cached, rendered take with ground truth;
    :func:`write_ground_truth` / :func:`load_ground_truth`.
``fake_cameras.device``
    :class:`FakeCamera` - the ``fake`` camera driver: real-time replay with clock
    offset, jitter, drops and disconnects.
``fake_cameras.rigs``
    :func:`simulated_rig_dict` / :func:`write_simulated_rig` - rig files of simulated cameras.
"""

from fake_cameras import device as _device  # noqa: E402, F401 (registers the "fake" driver)
