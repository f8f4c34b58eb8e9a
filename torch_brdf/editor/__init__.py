"""An interactive material editor in the browser.

Click an object of a precomputed view, pick a model, drag its parameters and see global
illumination update (Ben-Artzi et al. 2008's frozen polynomial renderer); compare with a
path-traced reference; look at the lobe. ``torch-brdf editor SCENE_OR_TENSORS`` serves the
page through Voilà; :class:`EditorApp` runs in JupyterLab too; :class:`EditorSession` is the
same editor without a user interface.
"""

from .params import ModelChoice, ParamSpec, model_choices, param_specs
from .session import EditorSession, ReferenceJob, load_source, object_id_buffer, scene_with_materials

__all__ = [
    "EditorSession",
    "ModelChoice",
    "ParamSpec",
    "ReferenceJob",
    "load_source",
    "model_choices",
    "object_id_buffer",
    "param_specs",
    "scene_with_materials",
]
