"""JSON Schemas of the haptex formats (asset, scene, KES, device); installed as ``haptex_compile.schemas``."""
