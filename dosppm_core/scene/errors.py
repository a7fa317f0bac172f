"""`SceneError`, in a module of its own so that modules `model` imports
(textures) can raise it too; `model` re-exports it."""


class SceneError(ValueError):
    """A user mistake in a scene; the message is one line naming where it is."""
