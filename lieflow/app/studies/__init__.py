"""Published studies that ``lieflow reproduce STUDY`` reruns with lieflow's public API, the
sweep machinery and the plugins (each study a module; :mod:`lieflow.app.reproduce` lists
them):

- :mod:`~lieflow.app.studies.modin_viviani_2020` — the long-time fate of 2D Euler on the
  sphere against ``γ = ‖L‖/√C₂`` (Modin & Viviani, J. Fluid Mech. 2020), with the
  ``lieflow-zeitlin`` plugin.
"""
