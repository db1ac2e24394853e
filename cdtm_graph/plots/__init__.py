"""Figures (matplotlib, Agg backend). A leaf: no core module imports from here."""

import matplotlib

matplotlib.use("Agg")
