"""Shared geometry and metrics, dataset readers, the method interface, and evaluation reports."""
