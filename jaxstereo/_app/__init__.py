"""The application: command line, batch campaigns, manifests, image and file input/output, figures."""
