"""The method: captures, model, rendering, training, relighting, meshes, evaluation, command line."""

__all__: list[str] = []
