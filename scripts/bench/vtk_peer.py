#!/usr/bin/python3
"""VTK's GPU volume ray caster (vtkGPUVolumeRayCastMapper, offscreen, same Mesa as the viewer)
rendering the volume viewer_bench rendered, from the same camera, at several sample distances.
Frame time includes the read-back, as the viewer's does (median of --reps frames after a
warm-up). Quality is the foreground PSNR (psnr_foreground: pixels where either image is not black,
the definition of vispack's render::diff_foreground) against VTK's own frame at a sample distance
of 0.125 voxel (its transfer functions differ from vispack's, so a PSNR against vispack's reference
would measure the difference of the colour mappings, not sampling error); the PSNR against
vispack's CPU reference is recorded too, for the record. One process renders each sample distance
once per repetition; scripts/bench/viewer_peers.py alternates this script with viewer_bench.
Usage: vtk_peer.py VIEWER_JSON RGBA_NRRD OUT_JSON [--reps N] [--factors F,F,...] [--ref-png PNG]
  --factors: sample distances in smallest voxel spacings (default 0.25,0.5,1,2; 1 when quick)
  --ref-png: vispack's CPU reference frame (viewer_bench --ref-png); VTK's fine frame is written
             beside it as viewer_vtk.png"""
import json
import os
import sys
import time

import numpy as np

from common import QUICK, median, write_json


def read_nrrd(path):
    data = open(path, "rb").read()
    i = data.index(b"\n\n")
    fields = {}
    for line in data[:i].decode().splitlines()[1:]:
        if ":" in line and not line.startswith("#"):
            k, v = line.split(":", 1)
            fields[k.strip()] = v.strip()
    sizes = [int(v) for v in fields["sizes"].split()]
    assert fields.get("encoding", "raw") == "raw", "expected a raw NRRD"
    assert fields["type"] in ("uchar", "unsigned char", "uint8"), fields["type"]
    arr = np.frombuffer(data[i + 2:], np.uint8).reshape(sizes[::-1])
    return arr, fields


def psnr_foreground(a, b, background=(0, 0, 0)):
    """Foreground PSNR in dB, as vispack's render::diff_foreground: a pixel is foreground when its
    RGB differs from the background in any channel in either image; 10 log10(255^2 / MSE), the MSE
    over the RGB of the foreground pixels; +inf when they are equal. Returns (dB, pixels, max diff)."""
    a = a[..., :3].astype(float)
    b = b[..., :3].astype(float)
    bg = np.asarray(background, float)
    fg = np.any(a != bg, axis=-1) | np.any(b != bg, axis=-1)
    n = int(fg.sum())
    err = (a[fg] - b[fg]) ** 2
    max_diff = int(np.sqrt(err.max())) if n else 0
    if n == 0 or err.sum() == 0:
        return float("inf"), n, max_diff
    return float(10 * np.log10(255.0 ** 2 / err.mean())), n, max_diff


def psnr_whole(a, b):
    mse = np.mean((a[..., :3].astype(float) - b[..., :3].astype(float)) ** 2)
    return float("inf") if mse == 0 else float(10 * np.log10(255.0 ** 2 / mse))


def main():
    import argparse
    ap = argparse.ArgumentParser()
    ap.add_argument("view_json")
    ap.add_argument("nrrd")
    ap.add_argument("out")
    ap.add_argument("--reps", type=int, default=1 if QUICK else 3)
    ap.add_argument("--factors", default="1" if QUICK else "0.25,0.5,1,2")
    ap.add_argument("--ref-png")
    a = ap.parse_args()
    view_json, nrrd, out = a.view_json, a.nrrd, a.out
    import vtk
    from vtk.util import numpy_support

    view = json.load(open(view_json))
    arr, fields = read_nrrd(nrrd)  # (z, y, x, 4)
    nz, ny, nx = arr.shape[:3]
    spacing = view["spacing_mm"]
    lo = view["box_lo"]
    img = vtk.vtkImageData()
    img.SetDimensions(nx, ny, nz)
    img.SetSpacing(*spacing)
    # Voxel centres: the viewer's box is [lo, hi] with voxel k centred at lo + (k + 0.5) spacing.
    img.SetOrigin(*[lo[i] + 0.5 * spacing[i] for i in range(3)])
    scalars = numpy_support.numpy_to_vtk(arr.reshape(-1, 4), deep=True,
                                         array_type=vtk.VTK_UNSIGNED_CHAR)
    scalars.SetNumberOfComponents(4)
    img.GetPointData().SetScalars(scalars)

    prop = vtk.vtkVolumeProperty()
    prop.IndependentComponentsOff()  # RGBA: colour from the first three, opacity from alpha
    prop.SetInterpolationTypeToLinear()
    opacity = vtk.vtkPiecewiseFunction()
    opacity.AddPoint(0, 0.0)
    opacity.AddPoint(255, float(view.get("opacity", 0.6)))
    prop.SetScalarOpacity(opacity)
    prop.ShadeOff()
    mapper = vtk.vtkGPUVolumeRayCastMapper()
    mapper.SetInputData(img)
    mapper.AutoAdjustSampleDistancesOff()
    mapper.SetBlendModeToComposite()
    volume = vtk.vtkVolume()
    volume.SetMapper(mapper)
    volume.SetProperty(prop)
    ren = vtk.vtkRenderer()
    ren.SetBackground(0, 0, 0)
    ren.AddVolume(volume)
    win = vtk.vtkRenderWindow()
    win.SetOffScreenRendering(1)
    win.AddRenderer(ren)
    size = int(view["size"])
    win.SetSize(size, size)
    cam = ren.GetActiveCamera()
    c = view["camera"]
    eye = np.array(c["eye"])
    cam.SetPosition(*eye)
    cam.SetFocalPoint(*(eye + 100.0 * np.array(c["forward"])))
    cam.SetViewUp(*c["up"])
    cam.SetViewAngle(c["fov_y_deg"])
    cam.SetClippingRange(c["near_mm"], c["far_mm"])
    if c.get("orthographic"):
        cam.ParallelProjectionOn()

    grab = vtk.vtkWindowToImageFilter()
    grab.SetInput(win)
    grab.SetInputBufferTypeToRGBA()
    grab.ReadFrontBufferOff()
    # One ray cast per timed frame: frame() renders once itself, and the filter's default
    # (ShouldRerender on) would render the scene a second time before reading it back, doubling
    # VTK's frame time against vispack's one render and one read-back.
    grab.ShouldRerenderOff()

    def frame():
        cam.Modified()
        win.Render()
        grab.Modified()
        grab.Update()
        o = grab.GetOutput()
        w, h, _ = o.GetDimensions()
        a = numpy_support.vtk_to_numpy(o.GetPointData().GetScalars()).reshape(h, w, -1)
        return a[::-1].copy()  # VTK rows are bottom-up

    t0 = time.perf_counter()
    frame()
    first = time.perf_counter() - t0
    smin = min(spacing)
    factors = [float(f) for f in a.factors.split(",")]
    ref_factor = 0.125
    mapper.SetSampleDistance(ref_factor * smin)
    ref = frame()
    vispack_ref = None
    try:
        import matplotlib.image as mpimg
    except ImportError:  # quick runs without the report need no matplotlib
        mpimg = None
    if mpimg and a.ref_png and os.path.exists(a.ref_png):
        vispack_ref = (mpimg.imread(a.ref_png)[..., :3] * 255).round().astype(np.uint8)
        mpimg.imsave(os.path.join(os.path.dirname(a.ref_png), "viewer_vtk.png"), ref[..., :3])
    rows = []
    for f in factors:
        mapper.SetSampleDistance(f * smin)
        img_f = frame()  # warm-up
        times = []
        for _ in range(a.reps):
            t0 = time.perf_counter()
            img_f = frame()
            times.append(time.perf_counter() - t0)
        db, n, worst = psnr_foreground(img_f, ref)
        row = {"sample_distance_voxels": f, "sample_distance_mm": f * smin,
               "ms": 1e3 * median(times), "times_ms": [1e3 * t for t in times],
               "psnr_db": db, "max_diff": worst, "foreground_pixels": n,
               "psnr_whole_frame_db": psnr_whole(img_f, ref),
               "psnr_vs_vispack_ref_db": psnr_foreground(img_f, vispack_ref)[0] if vispack_ref is not None else None}
        rows.append(row)
        print(f"vtk sample {f}: {row['ms']:.1f} ms, foreground {db:.2f} dB "
              f"(whole frame {row['psnr_whole_frame_db']:.1f} dB)", file=sys.stderr)
    caps = [l for l in win.ReportCapabilities().splitlines() if "renderer string" in l]
    write_json(out, {"renderer": caps[0].split(":", 1)[1].strip() if caps else "unknown",
                     "first_frame_s": first, "reference_sample_distance_voxels": ref_factor,
                     "size": size, "reps": a.reps, "rows": rows})


if __name__ == "__main__":
    main()
