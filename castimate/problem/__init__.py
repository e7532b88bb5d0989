"""Problem assembly: the YAML spec, parameter selection and the kinds as compositions of models."""
