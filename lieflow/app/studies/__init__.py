"""Published studies that ``lieflow reproduce STUDY`` reruns with lieflow's public API, the
sweep machinery and the plugins (:data:`lieflow.app.reproduce.STUDIES` lists them):

- :mod:`~lieflow.app.studies.modin_viviani_2020` — the long-time fate of 2D Euler on the
  sphere against ``γ = ‖L‖/√C₂`` (Modin & Viviani, J. Fluid Mech. 2020), with the
  ``lieflow-zeitlin`` plugin (a package: its plan, analysis, figure, report and the study
  as one call).

What the studies write besides their own results (output directory, Markdown tables, the
machine's description) comes from :mod:`lieflow.app.reports`, shared with the paper's
reproduction.
"""
