"""What the kinds get of the layer above them (the interface is kinds/services.py): binding,
relations, the update and the weight preview, handed to the kinds once, when the add-on is imported
(blender/__init__.py imports this module)."""

from __future__ import annotations

from contextlib import AbstractContextManager

import bpy

from . import binding
from .files import relations
from .kinds import services as kind_services
from .tools import weight_preview
from .update import evaluate


class BlenderServices:
    """`kinds.services.Services` over binding.py, relations.py, evaluate.py and weight_preview.py."""

    def quiet(self) -> AbstractContextManager[None]:
        return binding.quiet()

    def updates_suspended(self) -> bool:
        return binding.updates_suspended()

    def create(self, obj: bpy.types.Object, kind_id: str, name: str):
        return binding.create(obj, kind_id, name)

    def bind(self, obj: bpy.types.Object, deformer, depsgraph: bpy.types.Depsgraph,
             only: list[int] | None = None) -> None:
        binding.bind(obj, deformer, depsgraph, only)

    def reweight(self, obj: bpy.types.Object, deformer) -> None:
        binding.reweight(obj, deformer)

    def remove(self, obj: bpy.types.Object, index: int) -> None:
        binding.remove(obj, index)

    def sync(self, obj: bpy.types.Object, deformer) -> bool:
        return relations.sync(obj, deformer)

    def evaluate(self, obj: bpy.types.Object, depsgraph: bpy.types.Depsgraph) -> list[str]:
        return evaluate.evaluate_object(obj, depsgraph)

    def reweight_safely(self, obj: bpy.types.Object, deformer) -> None:
        binding.reweight_safely(obj, deformer)

    def rebind_safely(self, obj: bpy.types.Object, deformer, what: str) -> None:
        binding.rebind_safely(obj, deformer, what)

    def rebind_control_safely(self, obj: bpy.types.Object, deformer, index: int) -> None:
        binding.rebind_probe_safely(obj, deformer, index)

    def preview_option(self, deformer) -> None:
        weight_preview.on_option(deformer)


kind_services.provide(BlenderServices())
