"""The bpy layer: registration of properties, operators, panels and handlers."""


def register() -> None:
    pass


def unregister() -> None:
    pass
