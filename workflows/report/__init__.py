"""Figures and HTML of the analyses; nothing here computes a number that is judged."""

#: The module that draws the design's figure, by name: the design command forks a process
#: that imports it (matplotlib) beside its own imports (:class:`coupling.forked.Prepared`).
DESIGN_FIGURES = "workflows.report.design"
#: The module that draws ``predict``'s figure and page, forked alike by the predict command.
PREDICTION_FIGURES = "workflows.report.prediction"
