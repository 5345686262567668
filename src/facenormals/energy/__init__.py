"""Residual functions of the fitting energy (normal map, landmarks, statistical prior)."""

from facenormals.energy.residuals import landmark_residuals, normal_residuals, prior_residuals

__all__ = ["landmark_residuals", "normal_residuals", "prior_residuals"]
