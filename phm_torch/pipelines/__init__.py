"""Pipelines: the work of an app as a plain function of typed settings, between the Hydra entry points of
:mod:`phm_torch.apps` (compose a config, call, write) and the library (physics, data, surrogates, ...).

* :mod:`.generate`: the dataset store of the surrogates and the life split (``phm-generate``).
* :mod:`.train`: the surrogates from a dataset store (``phm-train``).

Nothing is imported here, so that importing one pipeline does not load the others' dependencies
(the training pipeline needs Lightning).
"""
