"""Input and output: mesh files in (meshio; hexahedra as they are, tetrahedra and closed
surfaces voxelised), fitted parameter sets out to other engines (JSON, VTU, SOFA), and the
figures of a calibration (matplotlib).

Modules: meshes, export, plot.
"""
