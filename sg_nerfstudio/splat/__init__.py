"""The reference model: the `sg-feature-splat` nerfstudio method, one file per role.

`method` (MethodSpecification, optimisers, schedules), `model` (feature-augmented splatfacto with the
speedup decoder), `datamanager` (images + cached teacher maps), `training` (the Trainer step by step on
CPU, for the demo, benchmarks and tests), `trained` (reading a trained run back: config, checkpoint,
dataparser frame). Nothing here imports registration.
"""
