"""The lab: the research tools around the library (``mcrs``). :mod:`mcrs_lab.campaign` runs the paper's
section-6 matrix (``mcrs-campaign``), :mod:`mcrs_lab.analysis` turns run directories and committed records
into figures, tables and the claims check (``mcrs-report``, ``mcrs-results``). The lab imports ``mcrs``;
``mcrs`` never imports the lab (tests/test_layering.py)."""
