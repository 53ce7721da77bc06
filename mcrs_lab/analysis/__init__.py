"""Figures and tables from run directories (``mcrs-report``): the paper's section 6."""
