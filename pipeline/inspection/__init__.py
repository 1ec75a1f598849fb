"""Inspection: alignment to CAD, deviations, deviation areas, colour maps, reports, scores."""
