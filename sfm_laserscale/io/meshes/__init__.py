"""Triangle meshes: reading for ray casting, and metric rescaling of mesh files.

:mod:`.mesh` is the entry point (``load_mesh``, ``write_scaled_mesh``, ``TriangleMesh``); it
dispatches on the file's extension to one module per format family: :mod:`.ply`, :mod:`.obj`,
:mod:`.gltf` (GLB/glTF), :mod:`.off_stl`; GLB/glTF, OFF and STL are read through trimesh.
:mod:`.common` holds what the formats share (streamed copies, atomic output files, side files,
fan triangulation).

Reading: PLY (ASCII, binary little/big endian) and OBJ with our own numpy readers; polygons are
fan-triangulated. Rescaling: PLY, OBJ, OFF and STL keep every byte except the vertex positions
(headers, faces, normals, colours, texture coordinates, custom properties); textures named by
the file (PLY ``comment TextureFile``, OBJ ``mtllib`` -> ``map_*``) are copied beside the output
with the same relative paths. Binary positions are scaled in their own type (product in float64,
rounded once); text positions are written with the shortest repr that reads back exactly.
GLB/glTF: the float POSITION accessors (and morph-target positions) are scaled inside the binary
buffers, accessor min/max and node translations with them; buffer bytes other than positions
are unchanged but the JSON is re-serialised (same content, other formatting); animations are not
scaled. glTF with Draco-compressed, quantised or sparse positions is refused (InputError).

Why our own PLY/OBJ code: plyfile reads list properties row by row in Python (slow on millions
of faces) and trimesh may merge/reorder vertices and splits OBJ files by material; both would
also make the byte-exact rewrite impossible.
"""
