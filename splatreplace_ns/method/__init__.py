"""The nerfstudio method ``splat-replace``: its specification, the pipeline that schedules the stages, the model,
and the ``splatreplace masks`` command. In: the datamanager's batches. Out: a trained, replaced scene."""
