"""Scenes: the one place a run's description becomes arrays, models, motions, obstacles and
contact.

* :mod:`.spec` - what a scene is: the pydantic models (frozen, validated; ``fem3d schema``).
* :mod:`.load` - reading one: by name, from a TOML file, around a mesh; :func:`apply_overrides`.
* :mod:`.keys` - key paths (``bodies[0].material.E``) that messages and overrides use.
* :mod:`.arrays` - the scene in arrays: meshes, transforms, selections, scripted pulls.
* :mod:`.build` - the scene built: model, pins, motions, damping, obstacles, contact
  (:func:`~fem3d.scene.build.build`, which :class:`fem3d.simulation.Simulation` calls).

This package re-exports the description and its reading (what ``fem3d.scene`` held before
the subpackages); building is imported from :mod:`fem3d.scene.build` (it loads the physics).
Inside the package imports go one way: :mod:`.keys`, then :mod:`.spec`, then :mod:`.arrays`,
then :mod:`.load` and :mod:`.build` (each imports only modules before it; none imports
:mod:`.build`).
"""

from fem3d.scene.load import (
    MESH_SCENE_DEFAULTS,
    apply_overrides,
    cache_dir,
    load_scene,
    mesh_scene,
    read_scene_file,
    scene_from_arrays,
    scene_names,
    scenes_dir,
)
from fem3d.scene.spec import (
    DEFAULT_STEPS,
    SURFACE_SUFFIXES,
    BodySpec,
    ContactSpec,
    DampingSpec,
    InteractionSpec,
    Keyframe,
    MaterialSpec,
    MeshObstacleSpec,
    MotionSpec,
    NewtonSpec,
    ObstacleSpec,
    OutputSpec,
    PinSpec,
    PlaneObstacleSpec,
    PreviewSpec,
    PullSpec,
    RegionSpec,
    Scene,
    Selector,
    SimulationSpec,
    TetrahedralizeSpec,
    TransformSpec,
    material_names,
    scene_schema,
)

__all__ = [
    "Scene", "SimulationSpec", "NewtonSpec", "BodySpec", "MaterialSpec", "RegionSpec",
    "Selector", "PinSpec", "MotionSpec", "Keyframe", "PullSpec", "ContactSpec",
    "ObstacleSpec", "PlaneObstacleSpec", "MeshObstacleSpec", "OutputSpec", "PreviewSpec",
    "InteractionSpec", "TransformSpec", "TetrahedralizeSpec", "DampingSpec",
    "load_scene", "apply_overrides", "scene_schema", "scenes_dir", "scene_names",
    "scene_from_arrays", "mesh_scene", "read_scene_file", "cache_dir", "material_names",
    "DEFAULT_STEPS", "MESH_SCENE_DEFAULTS", "SURFACE_SUFFIXES",
]
