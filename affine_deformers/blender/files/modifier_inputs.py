"""The values on a Geometry Nodes modifier's inputs: the one place that reads and writes them.

Blender has stored them two ways, and this module picks the one the running Blender offers by
looking at the modifier, not at a version number:

* ID properties of the modifier (4.2 to 5.1): ``mod[identifier]`` holds the value, with
  ``mod[identifier + "_use_attribute"]`` and ``mod[identifier + "_attribute_name"]`` beside it for
  inputs that can read an attribute;
* RNA properties (5.2 on): ``mod.properties.inputs.<identifier>`` is a struct with ``value``,
  ``type`` (``'VALUE'`` or ``'ATTRIBUTE'``) and ``attribute_name``; the modifier itself takes no ID
  properties there.

`identifier` is the group interface socket's identifier ("Socket_1"). A missing input reads as None
(as an absent ID property did); writing one that does not exist raises KeyError. Neither storage
available raises `UnsupportedInputsError`, which names the running Blender.
"""

from __future__ import annotations

from typing import Any

import bpy

_USE_ATTRIBUTE = "_use_attribute"
_ATTRIBUTE_NAME = "_attribute_name"


class UnsupportedInputsError(RuntimeError):
    """This Blender keeps a modifier's input values in a way this add-on does not know."""


def _rna_inputs(mod: bpy.types.Modifier) -> Any | None:
    """`mod.properties.inputs` where the running Blender stores inputs as RNA properties, else None."""
    properties = getattr(mod, "properties", None)
    return getattr(properties, "inputs", None) if properties is not None else None


def stores_as_rna() -> bool:
    """Whether this Blender keeps modifier inputs as RNA properties (5.2 on), from the RNA itself."""
    return "properties" in bpy.types.NodesModifier.bl_rna.properties


def _unsupported(mod: bpy.types.Modifier) -> UnsupportedInputsError:
    return UnsupportedInputsError(
        f"Blender {bpy.app.version_string} stores the inputs of Geometry Nodes modifier '{mod.name}' in "
        "a way Affine Deformers does not know (neither ID properties nor properties.inputs): update the "
        "add-on")


def _socket(mod: bpy.types.Modifier, identifier: str) -> Any | None:
    """The RNA struct of one input (5.2 on), or None when the group has no such input."""
    inputs = _rna_inputs(mod)
    return getattr(inputs, identifier, None) if inputs is not None else None


def value(mod: bpy.types.Modifier, identifier: str | None) -> Any | None:
    """The value on the input `identifier` of `mod` (a string, number, ID or None when unset or
    missing)."""
    if not identifier:
        return None
    inputs = _rna_inputs(mod)
    if inputs is not None:
        socket = getattr(inputs, identifier, None)
        return getattr(socket, "value", None)  # a geometry input has none
    try:
        return mod.get(identifier)
    except TypeError:  # no ID properties either
        raise _unsupported(mod) from None


def set_value(mod: bpy.types.Modifier, identifier: str, new: Any) -> bool:
    """Put `new` on the input `identifier` of `mod`; True when it changed. Like an ID property
    assignment it does not tag the modifier's relations: callers re-assign the node group for that."""
    if value(mod, identifier) == new:
        return False
    if _rna_inputs(mod) is not None:
        socket = _socket(mod, identifier)
        if socket is None:
            raise KeyError(f"modifier '{mod.name}' has no input '{identifier}'")
        socket.value = new
        return True
    try:
        mod[identifier] = new
    except TypeError:
        raise _unsupported(mod) from None
    return True


def uses_attribute(mod: bpy.types.Modifier, identifier: str) -> bool:
    """Whether the input `identifier` reads an attribute instead of its value."""
    socket = _socket(mod, identifier)
    if socket is not None:
        return getattr(socket, "type", "VALUE") == "ATTRIBUTE"
    if _rna_inputs(mod) is not None:
        return False
    return bool(value(mod, identifier + _USE_ATTRIBUTE))


def attribute_name(mod: bpy.types.Modifier, identifier: str) -> str:
    """The attribute the input `identifier` names (used or not; '' when none)."""
    socket = _socket(mod, identifier)
    if socket is not None:
        return getattr(socket, "attribute_name", "")
    if _rna_inputs(mod) is not None:
        return ""
    name = value(mod, identifier + _ATTRIBUTE_NAME)
    return name if isinstance(name, str) else ""


def set_attribute(mod: bpy.types.Modifier, identifier: str, name: str | None) -> bool:
    """Make the input `identifier` read the attribute `name`, or its own value again (None). True when
    it changed. Raises ValueError for an input that cannot read an attribute."""
    use = name is not None
    if uses_attribute(mod, identifier) == use and (not use or attribute_name(mod, identifier) == name):
        return False
    if _rna_inputs(mod) is not None:
        socket = _socket(mod, identifier)
        if socket is None:
            raise KeyError(f"modifier '{mod.name}' has no input '{identifier}'")
        if "attribute_name" not in socket.bl_rna.properties:
            raise ValueError(f"input '{identifier}' of modifier '{mod.name}' cannot read an attribute")
        if use:
            socket.attribute_name = name
        socket.type = "ATTRIBUTE" if use else "VALUE"
        return True
    if value(mod, identifier + _USE_ATTRIBUTE) is None:
        raise ValueError(f"input '{identifier}' of modifier '{mod.name}' cannot read an attribute")
    mod[identifier + _USE_ATTRIBUTE] = use
    if use:
        mod[identifier + _ATTRIBUTE_NAME] = name
    return True


def data_path(mod: bpy.types.Modifier, identifier: str) -> str:
    """The RNA path of the input's value from the object (for keyframes, drivers and overrides)."""
    base = f'modifiers["{bpy.utils.escape_identifier(mod.name)}"]'
    if _rna_inputs(mod) is not None:
        return f"{base}.properties.inputs.{identifier}.value"
    return f'{base}["{identifier}"]'
