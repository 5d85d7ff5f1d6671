"""Simulated units, load schedules, indenters of other shapes than a sphere, and simulated datasets.

It imports `physics`, `data` and the foundation modules, never `observe`.
"""

from ._contacts import (
    CONTACT_FAMILIES as CONTACT_FAMILIES,
    CONTACT_SHAPES as CONTACT_SHAPES,
    contact_summary as contact_summary,
    grasp_limits as grasp_limits,
    Indenter as Indenter,
    indenter_deformation as indenter_deformation,
    indenter_tractions as indenter_tractions,
    IndenterFrame as IndenterFrame,
    random_indenters as random_indenters,
    shape_schedule as shape_schedule,
    traction_deformation as traction_deformation,
)
from ._scene import (
    BACKDROP_RGB as BACKDROP_RGB,
    empty_scene_reference as empty_scene_reference,
    render_scene as render_scene,
    scene_defocus as scene_defocus,
    scene_disc as scene_disc,
    SCENE_KINDS as SCENE_KINDS,
    scene_magnification as scene_magnification,
    scene_rectangle as scene_rectangle,
    scene_reflectance as scene_reflectance,
    scene_ring as scene_ring,
    scene_schedule as scene_schedule,
    SCENE_SHAPES as SCENE_SHAPES,
    scene_summary as scene_summary,
    scene_texture as scene_texture,
    SCENE_TEXTURES as SCENE_TEXTURES,
    SceneFrame as SceneFrame,
    SceneObject as SceneObject,
)
from ._simulate import (
    Deviations as Deviations,
    load_schedule as load_schedule,
    LoadSchedule as LoadSchedule,
    perturb_device as perturb_device,
    simulate_dataset as simulate_dataset,
    Simulator as Simulator,
)
