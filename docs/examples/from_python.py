"""Calibrate a camera, correct an image and reconstruct a room, from Python (docs/guides/python_api.md).

Runs on radiomap's simulated sample recordings of one camera (bracketed exposures, a white-paper sweep and
a room walk), made on first use and cached: python docs/examples/from_python.py [OUTPUT_FOLDER]
"""

import sys
from pathlib import Path

import mapping
import radiometry
from mapping.simulation import sample_sequence
from radiometry.images import read_rgb, write_image

out = Path(sys.argv[1] if len(sys.argv) > 1 else "from_python_out")
out.mkdir(parents=True, exist_ok=True)

# 1. the camera response from bracketed exposures (a folder of images and its times.txt)
response = radiometry.calibrate_response(sample_sequence("brackets"))
response.save(out / "crf.npz")

# 2. vignetting from a white-paper sweep, through that response (a per-pixel LUT; model="poly" for a polynomial)
vignetting = radiometry.calibrate_vignetting(sample_sequence("paper") / "rgb", response)
vignetting.save(out / "vignetting.npz")

# 3. one image corrected: I' = f(f^-1(I) / V), uint8 RGB (irradiance=True gives float32 f^-1(I) / V)
room = sample_sequence("room")
image = read_rgb(sorted((room / "rgb").glob("*.png"))[0])
write_image(out / "corrected.png", radiometry.correct(image, response, vignetting))

# 4. the room fused in irradiance: ICP poses, exposure compensation on (the default with a response);
#    keywords are radiomap reconstruct's options (--depth-max -> depth_max); output=None writes nothing
result = mapping.reconstruct_sequence(room, response=response, vignetting=vignetting, depth_max=5.0)
print(result)                                   # frames fused, mean colour disagreement (L1)
print("ATE", "-" if result.ate is None else f"{100 * result.ate.rmse:.2f} cm")

mesh = result.mesh_trimesh()                    # trimesh.Trimesh, display colours (as mesh.ply holds them)
mesh.export(out / "room.ply")
o3d_mesh = result.mesh_open3d()                 # open3d.geometry.TriangleMesh, the same colours in [0, 1]
print(f"mesh: {len(mesh.vertices)} vertices, {len(o3d_mesh.triangles)} triangles -> {out / 'room.ply'}")
