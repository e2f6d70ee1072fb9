"""Files, links and overrides: what is saved in the .blend (bind data as attributes, the node group and its
modifier, the depsgraph relations) and what keeps a rig right when it travels (library overrides' carriers
and input modifier, copied modifiers, instanced linked rigs)."""
