"""A Geometry Nodes modifier's inputs through files/modifier_inputs.py, the one place that reads and
writes them, on whichever storage the running Blender has (ID properties up to 5.1, RNA
`properties.inputs` from 5.2): values of every type the add-on uses, "use attribute" and the
attribute's name, a missing input, and the data path a keyframe takes."""

from __future__ import annotations

import importlib

import bpy
import pytest


@pytest.fixture
def inputs(installed):
    return importlib.import_module(f"{installed.package}.blender.files.modifier_inputs")


def _modifier():
    ng = bpy.data.node_groups.new("Inputs", "GeometryNodeTree")
    ng.is_modifier = True
    ng.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    sockets = {kind: ng.interface.new_socket(kind, in_out="INPUT", socket_type=f"NodeSocket{kind}")
               .identifier for kind in ("String", "Object", "Collection", "Float")}
    ng.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    bpy.ops.mesh.primitive_cube_add()
    obj = bpy.context.active_object
    mod = obj.modifiers.new("Inputs", "NODES")
    mod.node_group = ng
    return obj, mod, sockets


def test_values_attributes_and_paths_on_this_blender(bl, inputs):
    obj, mod, sockets = _modifier()
    collection = bpy.data.collections.new("Held")
    for kind, value in (("String", "affdef_x_offset"), ("Object", obj), ("Collection", collection),
                        ("Float", 2.5)):
        identifier = sockets[kind]
        assert inputs.set_value(mod, identifier, value) is True
        assert inputs.value(mod, identifier) == value, kind
        assert inputs.set_value(mod, identifier, value) is False, "unchanged: nothing written"
    assert inputs.value(mod, "Socket_99") is None and inputs.value(mod, None) is None
    if inputs.stores_as_rna():  # an ID property of any name could be set; an RNA input must exist
        with pytest.raises(KeyError, match="no input 'Socket_99'"):
            inputs.set_value(mod, "Socket_99", 1.0)
    float_input = sockets["Float"]
    assert not inputs.uses_attribute(mod, float_input)
    assert inputs.set_attribute(mod, float_input, "height") is True
    assert inputs.uses_attribute(mod, float_input) and inputs.attribute_name(mod, float_input) == "height"
    assert inputs.set_attribute(mod, float_input, None) is True
    assert not inputs.uses_attribute(mod, float_input)
    with pytest.raises(ValueError, match="cannot read an attribute"):
        inputs.set_attribute(mod, sockets["String"], "name")
    path = inputs.data_path(mod, float_input)
    assert obj.path_resolve(path) == 2.5
    assert obj.keyframe_insert(data_path=path, frame=1)
    assert inputs.stores_as_rna() == (bpy.app.version >= (5, 2, 0)), "the storage found is Blender's own"
