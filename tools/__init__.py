"""Maintenance tools that are not benchmarks: ``python -m tools.remesh`` (remeshed dev data with
ground truth carried, into ``bench/data``) and ``python -m tools.ship_model`` (a trained
checkpoint shipped as a pretrained model under ``torchfmap/nn/models``)."""
