"""BOP-format datasets (T-LESS and any other BOP dataset): the reader, the RoI pipeline, a renderer
for object meshes and a small BOP-format fixture the project makes itself."""
