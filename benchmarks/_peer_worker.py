"""Render the benchmark scene with one peer code, in that peer's own environment.

Run by `bench_jax_peers.py` as ``<peer venv>/bin/python benchmarks/_peer_worker.py
JOB.npz OUT.npz``; imports neither clumpylen_jax nor JAX unless the peer needs it
(caustics runs on PyTorch). JOB.npz holds the scene (detector grid, PSF kernel,
deflection map or SIS, clump parameters in this project's convention, the mask of
the detector pixels to supersample) and the settings to time; OUT.npz gets, for
each setting, the image (counts/s per detector pixel, PSF at detector sampling)
and its cold / warm seconds.

Both peers are sampled the way lenstronomy's ``compute_mode="adaptive"`` samples
(bench_lenstronomy.py): the masked detector pixels at ss × ss point samples
(sub-pixel centres), every other pixel at its centre, the mean times the pixel
area, then the PSF at detector sampling.
- JAXtronomy: its own ``ImageModel`` with ``kwargs_numerics`` compute_mode
  "adaptive" (``jaxtronomy.ImSim.Numerics.numerics.Numerics``), ``SIS`` lens,
  ``SERSIC_ELLIPSE`` light (lenstronomy's convention; `smoothing` set to 1e-9"),
  in batches of JAXTRONOMY_BATCH clumps (one compiled model, called per batch).
- caustics (PyTorch): its ``LensSource`` simulator supersamples the whole field
  (``upsample_factor``, no adaptive mode), which at ss = 144 is 1.7e8 rays for
  this 90 × 90 field; so its lens's ``raytrace`` and its ``LightStack`` of
  ``Sersic`` sources are called on the same sub-pixel centres as above (in chunks
  of CHUNK points, under ``torch.no_grad``), float64, and the PSF applied with
  ``torch.nn.functional.conv2d`` (what ``LensSource`` does with psf_mode
  "conv2d"). ``LensSource`` itself (full field, psf_convolve=False) is used for
  the same-rays check at ss = 12.
"""

from __future__ import annotations

import sys
import time

import numpy as np

CHUNK = 1 << 21
# JAXtronomy evaluates every profile on every sample at once: 100 clumps at ss = 216 (1.8e7
# samples) was killed for memory and batches of 30 took 8.7 GB; so the image is the sum of
# calls of one compiled model on batches of this many clumps (the image is linear in the
# source); ~3 GB at ss = 216
JAXTRONOMY_BATCH = 10


def subpixel_points(job, ss):
    """(x, y, owner) of the adaptive sampling: ss² sub-pixel centres in masked pixels."""
    nx, ny = int(job["nx"]), int(job["ny"])
    pix = float(job["pixel"])
    x0, y0 = float(job["x0"]), float(job["y0"])
    mask = job["mask"].astype(bool)
    jj, ii = np.nonzero(mask)
    off = (np.arange(ss) + 0.5) / ss - 0.5
    ox, oy = np.meshgrid(off, off)
    xs = (x0 + ii[:, None] * pix + ox.ravel()[None, :] * pix).ravel()
    ys = (y0 + jj[:, None] * pix + oy.ravel()[None, :] * pix).ravel()
    owner = np.repeat(jj * nx + ii, ss * ss)
    uj, ui = np.nonzero(~mask)
    xs = np.concatenate([xs, x0 + ui * pix])
    ys = np.concatenate([ys, y0 + uj * pix])
    owner = np.concatenate([owner, uj * nx + ui])
    weight = np.where(np.arange(len(xs)) < mask.sum() * ss * ss, 1.0 / (ss * ss), 1.0)
    return xs, ys, owner, weight, (ny, nx)


# ------------------------------------------------------------------ caustics (PyTorch)
class CausticsScene:
    def __init__(self, job, ss, full_field=False):
        import torch
        import caustics
        from caustics.light.func import k_sersic
        torch.set_default_dtype(torch.float64)
        self.torch, self.job, self.ss = torch, job, ss
        cosmo = caustics.FlatLambdaCDM(name="cosmo")
        if str(job["lens"]) == "map":
            dmap = torch.tensor(np.stack([job["map_a1"], job["map_a2"]]))
            self.lens = caustics.PixelatedDeflection(
                pixelscale=float(job["map_pixel"]), cosmology=cosmo, z_l=0.5, z_s=1.0,
                x0=float(job["map_center"][0]), y0=float(job["map_center"][1]),
                deflection_map=dmap, name="lens")
        else:
            self.lens = caustics.SIS(cosmology=cosmo, z_l=0.5, z_s=1.0, x0=0.0, y0=0.0,
                                     Rein=float(job["theta_e"]), name="lens")
        srcs = []
        for k in range(len(job["re"])):
            n = float(job["n"][k])
            kc = float(k_sersic(torch.tensor(n)))
            b = float(job["b_exact"][k])
            # caustics: Ie exp(-k((e/Re)^(1/n) - 1)), e = sqrt(x'^2 + (y'/q)^2): Re on the major axis
            srcs.append(caustics.Sersic(
                x0=float(job["center"][k, 0]), y0=float(job["center"][k, 1]),
                q=float(job["q"][k]), phi=float(job["pa"][k]), n=n,
                Re=float(job["re"][k]) * (kc / b) ** n,
                Ie=float(job["i0"][k]) * np.exp(-kc), name=f"s{k}"))
        self.source = caustics.LightStack(srcs, name="stack")
        self.kernel = torch.tensor(job["psf"])
        if full_field:
            # LensSource samples sub-pixel centres of a field centred on (x0, y0)
            nx, ny, pix = int(job["nx"]), int(job["ny"]), float(job["pixel"])
            cx = float(job["x0"]) + (nx - 1) * pix / 2
            cy = float(job["y0"]) + (ny - 1) * pix / 2
            self.sim = caustics.LensSource(self.lens, self.source, pixelscale=pix, pixels_x=nx,
                                           pixels_y=ny, upsample_factor=ss, x0=cx, y0=cy,
                                           name="sim")
            self.sim.to(dtype=torch.float64)
        else:
            self.sim = None
            xs, ys, owner, weight, self.shape = subpixel_points(job, ss)
            self.xs, self.ys = torch.tensor(xs), torch.tensor(ys)
            self.owner, self.weight = torch.tensor(owner), torch.tensor(weight)

    def render(self):
        torch = self.torch
        pix = float(self.job["pixel"])
        with torch.no_grad():
            if self.sim is not None:
                img = self.sim(psf_convolve=False) * pix**2
            else:
                vals = []
                for s in range(0, len(self.xs), CHUNK):
                    bx, by = self.lens.raytrace(self.xs[s:s + CHUNK], self.ys[s:s + CHUNK])
                    vals.append(self.source.brightness(bx, by))
                v = torch.cat(vals) * self.weight * pix**2
                img = torch.zeros(self.shape[0] * self.shape[1]).index_add_(0, self.owner, v)
                img = img.reshape(self.shape)
            out = torch.nn.functional.conv2d(img[None, None], torch.flip(self.kernel, (0, 1))[None, None],
                                             padding="same")[0, 0]
        return out.numpy()


# ------------------------------------------------------------------ JAXtronomy
class JaxtronomyScene:
    def __init__(self, job, ss, full_field=False):
        import jax
        jax.config.update("jax_enable_x64", True)
        from lenstronomy.Data.pixel_grid import PixelGrid
        from lenstronomy.Data.psf import PSF
        from jaxtronomy.ImSim.image_model import ImageModel
        from jaxtronomy.LensModel.lens_model import LensModel
        from jaxtronomy.LightModel.light_model import LightModel
        nx, ny, pix = int(job["nx"]), int(job["ny"]), float(job["pixel"])
        pg = PixelGrid(nx=nx, ny=ny, transform_pix2angle=np.diag([pix, pix]),
                       ra_at_xy_0=float(job["x0"]), dec_at_xy_0=float(job["y0"]))
        psf = PSF(psf_type="PIXEL", kernel_point_source=job["psf"])
        numerics = dict(supersampling_factor=ss, supersampling_convolution=False)
        if not full_field:
            numerics.update(compute_mode="adaptive", supersampled_indexes=job["mask"].astype(bool))
        nc = min(len(job["lt_amp"]), JAXTRONOMY_BATCH)
        light = LightModel(["SERSIC_ELLIPSE"] * nc,
                           profile_kwargs_list=[dict(smoothing=float(job["lt_smoothing"]))] * nc)
        assert str(job["lens"]) == "sis", "JAXtronomy has no interpolated deflection lens"
        self.model = ImageModel(pg, psf, lens_model_class=LensModel(["SIS"]),
                                source_model_class=light, kwargs_numerics=numerics)
        self.kw_lens = [dict(theta_E=float(job["theta_e"]), center_x=0.0, center_y=0.0)]
        keys = ("amp", "R_sersic", "n_sersic", "e1", "e2", "center_x", "center_y")
        kw = [{k: float(job["lt_" + k][i]) for k in keys} for i in range(len(job["lt_amp"]))]
        while len(kw) % nc:                         # pad the last batch with dark clumps
            kw.append(dict(kw[0], amp=0.0))
        self.batches = [kw[i:i + nc] for i in range(0, len(kw), nc)]

    def render(self):
        import jax
        img = 0.0
        for kw in self.batches:    # one compiled model, called once per batch of clumps
            img = img + self.model.image(kwargs_lens=self.kw_lens, kwargs_source=kw)
        return np.asarray(jax.block_until_ready(img))


PEERS = {"caustics": CausticsScene, "jaxtronomy": JaxtronomyScene}


def version(peer):
    import importlib.metadata as md
    out = {peer: md.version(peer)}
    for dep in ("torch", "jax", "lenstronomy"):
        try:
            out[dep] = md.version(dep)
        except md.PackageNotFoundError:
            pass
    return out


def main(job_path, out_path):
    job = dict(np.load(job_path, allow_pickle=False))
    peer = str(job["peer"])
    t = time.perf_counter()
    __import__(peer)
    out = dict(import_s=time.perf_counter() - t, versions=str(version(peer)))
    for i, (ss, repeats, full) in enumerate(job["settings"]):
        t = time.perf_counter()
        scene = PEERS[peer](job, int(ss), full_field=bool(full))
        img = scene.render()
        cold = time.perf_counter() - t
        times = []
        for _ in range(int(repeats)):
            t = time.perf_counter()
            scene.render()
            times.append(time.perf_counter() - t)
        out[f"img{i}"] = img
        out[f"cold{i}"] = cold
        out[f"warm{i}"] = float(np.median(times)) if times else np.nan
        print(f"{peer} ss={ss} full={full}: cold {cold:.3g} s, warm {out[f'warm{i}']:.3g} s",
              flush=True)
        del scene
    np.savez(out_path, **out)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
