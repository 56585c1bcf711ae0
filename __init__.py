"""ShapeGen Blender extension entry point: register / unregister, nothing else.

Everything Blender-specific lives in `shapegen_addon/`; the algorithms live in `core/`
(a plain numpy/scipy library that never imports bpy).
"""


def register():
    from .shapegen_addon import register as register_addon

    register_addon()


def unregister():
    from .shapegen_addon import unregister as unregister_addon

    unregister_addon()
