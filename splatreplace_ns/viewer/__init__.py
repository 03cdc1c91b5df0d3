"""viser viewer interaction: selecting instances with clicks."""
