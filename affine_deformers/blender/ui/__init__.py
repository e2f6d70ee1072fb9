"""The interface: panels and menus, the deformer operators, how operators address a deformer, and the add-on
preferences."""
