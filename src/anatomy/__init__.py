"""Patient anatomy: from a lumen surface (STL, OBJ, PLY) to the Tissue FMU's wall mesh and the catheter's path.

A vascular surgeon's data arrive as the inner wall of the vessel, a triangle mesh exported from a
segmentation (3D Slicer, VMTK, ITK-SNAP). This package reads and checks such a surface
(:mod:`anatomy.surface`), builds the tetrahedral wall outside it (:mod:`anatomy.wall`), computes the
vessel's centerline with its radius (:mod:`anatomy.centerline`) and generates a family of parametric
aneurysms that take the same path (:mod:`anatomy.family`).

It runs once, before a simulation: the Tissue FMU reads the wall it writes as a mesh file and
carries none of this package (nor trimesh) in its runtime.

Conventions: SI units (metres) once read; a lumen surface's triangles are wound so that their
normals point out of the lumen, into the wall; the vessel's open ends (where the segmentation cut
it) are boundary loops of the surface.
"""
