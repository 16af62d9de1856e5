#!/usr/bin/python3
"""VTK's GPU volume ray caster (vtkGPUVolumeRayCastMapper, offscreen, same Mesa as the viewer)
rendering the volume viewer_bench rendered, from the same camera, at several sample distances.
Frame time includes the read-back, as the viewer's does. PSNR is against VTK's own frame at the
finest sample distance (its transfer functions differ from vispack's, so a PSNR against vispack's
reference would measure the difference of the colour mappings, not sampling error); the PSNR
against vispack's CPU reference is recorded too, for the record.
Usage: vtk_peer.py VIEWER_JSON RGBA_NRRD OUT_JSON"""
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


def psnr(a, b):
    mse = np.mean((a[..., :3].astype(float) - b[..., :3].astype(float)) ** 2)
    return float("inf") if mse == 0 else float(10 * np.log10(255.0 ** 2 / mse))


def main():
    view_json, nrrd, out = sys.argv[1:4]
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
    factors = [1.0] if QUICK else [0.25, 0.5, 1.0, 2.0]
    ref_factor = 0.125
    mapper.SetSampleDistance(ref_factor * smin)
    ref = frame()
    vispack_ref = None
    ref_png = os.path.join(os.path.dirname(out), "viewer_ref.png")
    try:
        import matplotlib.image as mpimg
        if os.path.exists(ref_png):
            vispack_ref = (mpimg.imread(ref_png)[..., :3] * 255).round().astype(np.uint8)
            mpimg.imsave(os.path.join(os.path.dirname(out), "viewer_vtk.png"), ref[..., :3])
    except ImportError:
        pass
    rows = []
    reps = 1 if QUICK else 3
    for f in factors:
        mapper.SetSampleDistance(f * smin)
        img_f = frame()  # warm-up
        times = []
        for _ in range(reps):
            t0 = time.perf_counter()
            img_f = frame()
            times.append(time.perf_counter() - t0)
        rows.append({"sample_distance_voxels": f, "sample_distance_mm": f * smin,
                     "ms": 1e3 * median(times), "times_ms": [1e3 * t for t in times],
                     "psnr_db": psnr(img_f, ref),
                     "psnr_vs_vispack_ref_db": psnr(img_f, vispack_ref) if vispack_ref is not None else None})
        print(f"vtk sample {f}: {rows[-1]['ms']:.0f} ms, {rows[-1]['psnr_db']:.1f} dB", file=sys.stderr)
    caps = [l for l in win.ReportCapabilities().splitlines() if "renderer string" in l]
    write_json(out, {"renderer": caps[0].split(":", 1)[1].strip() if caps else "unknown",
                     "first_frame_s": first, "reference_sample_distance_voxels": ref_factor,
                     "size": size, "rows": rows})


if __name__ == "__main__":
    main()
