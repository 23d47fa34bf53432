"""Experiment runners: they own loops, evaluation against ground truth and output folders."""
