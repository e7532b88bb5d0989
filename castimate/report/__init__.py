"""Reports: HTML with matplotlib figures, built from a solved output directory."""
