"""Campaigns (``hilsim campaign``): a matrix of missions or renders, run locally or on Ray.

Format: scenarios/CAMPAIGNS.md. Modules: :mod:`spec` (the file), :mod:`matrix`
(cases, scenario copies), :mod:`criteria` (pass criteria), :mod:`mission` (one
run: bridge + stack), :mod:`metrics` (truth metrics), :mod:`render` and
:mod:`labels` (render campaigns), :mod:`executors` (local pool, Ray),
:mod:`results` and :mod:`report` (the outputs), :mod:`runner` (all of it).
"""
