"""A scene: the objects, lights and camera (`model`), materials and textures (`materials`), scene files
(`file`), their generated reference (`formats`) and components from other packages (`plugins`)."""
