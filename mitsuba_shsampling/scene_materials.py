"""A scene's materials: its distinct BSDF instances, and the names reports give them.

Shapes that share a BSDF instance share a material. A material is named by its
BSDF's id when the scene gives one, else by the ids of the shapes that use it
(``shape3`` for a shape without an id, numbered in an order that is the same in every
process: :func:`scene_materials`). A BSDF nested in a shape's dictionary
(``load_dict``) gets its key, ``bsdf``, as id: that names no material. Lanes know their material by the BSDF's
Dr.Jit registry id (``dr.reinterpret_array(mi.UInt32, si.bsdf())``).
"""

from __future__ import annotations

import dataclasses

import drjit as dr
import mitsuba as mi


@dataclasses.dataclass
class Material:
    bsdf: mi.BSDF
    shapes: list
    """Ids of the shapes that use it."""

    @property
    def name(self) -> str:
        given = self.bsdf.id()
        return given if given and given != "bsdf" and not given.startswith("_unnamed") else "+".join(self.shapes)

    @property
    def plugin(self) -> str:
        text = str(self.bsdf)
        return "Principled" if text.startswith("Principled") else text.split("[", 1)[0].strip()


def registry_id(obj) -> int:
    """Id under which Dr.Jit's registry knows a BSDF or shape: the per-lane value of
    ``dr.reinterpret_array(mi.UInt32, si.bsdf())`` (or ``si.shape``) where it is hit."""
    pointer = mi.BSDFPtr(obj) if isinstance(obj, mi.BSDF) else mi.ShapePtr(obj)
    return int(dr.reinterpret_array(mi.UInt32, pointer)[0])


def shape_order_key(shape: mi.Shape) -> tuple:
    """What orders a scene's shapes the same way in every process: its id, its plugin, its
    bounding box and its primitive count. Mitsuba loads a scene's objects in parallel, so
    ``scene.shapes()`` lists them in an order that changes from run to run (a material
    named by a shape's position was ``shape2`` in one process and ``shape3`` in the next,
    and a plan or a ``strategy`` entry naming it did not carry over)."""
    box = shape.bbox()
    return (shape.id(), shape.class_name(), tuple(box.min), tuple(box.max), int(shape.primitive_count()))


def scene_materials(scene: mi.Scene) -> list[Material]:
    """The scene's materials, in the order of their first use by the shapes sorted by
    :func:`shape_order_key` (the same in every process); a shape without an id is named
    by its position in that order."""
    materials: list[Material] = []
    for number, shape in enumerate(sorted(scene.shapes(), key=shape_order_key)):
        bsdf = shape.bsdf()
        if bsdf is None:
            continue
        material = next((m for m in materials if m.bsdf is bsdf), None)
        if material is None:
            material = Material(bsdf, [])
            materials.append(material)
        material.shapes.append(shape.id() or f"shape{number}")
    return materials
