"""Figures and HTML of the analyses; nothing here computes a number that is judged."""
