"""Files: meshes, configs, model and fit files, replay folders, EXR images, atomic writes."""
