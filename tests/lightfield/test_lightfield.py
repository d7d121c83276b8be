"""The light field from radiance sphere grids (python -m pipeline lightfield) against analytic truth.

Every grid here is written by the test in the documented grid format
(docs/light-field.md) from a radiance distribution whose light-field
quantities are known in closed form, independently of the package's
quadrature: L = A + B cos z, and L = C exp(k cos z) (1 + eps sin z cos phi)
(the azimuthal term integrates to zero in every quantity). A grid written
this way samples L at the cell centres (cell_values = centre). The tolerances
are the uncertainties the output states.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
import xarray as xr
from scipy import integrate

from pipeline.cli import main
from pipeline.lightfield.command import compute_light_field

UNITS = "W m-2 sr-1 nm-1"
GRID_DEG = 2.0
CONE_DEG = 5.0   # the schema's default radiance_cone_half_angle_deg


def centres(grid_deg=GRID_DEG):
    nz, na = int(round(180 / grid_deg)), int(round(360 / grid_deg))
    return (np.arange(nz) + 0.5) * grid_deg, (np.arange(na) + 0.5) * grid_deg


def write_grid(path, radiance, grid_deg=GRID_DEG, random_sigma=None, systematic_sigma=None, medium="water",
               times=None, units=UNITS, drop=()):
    """A grid file in the documented format: dims (frame, band, zenith, azimuth), one band."""
    z, a = centres(grid_deg)
    rad = np.asarray(radiance, float)
    rad = rad.reshape((-1, 1) + rad.shape[-2:])
    dims = ("frame", "band", "zenith", "azimuth")
    data = {"sphere_radiance": (dims, rad, {"units": units})}
    if random_sigma is not None:
        data["sphere_radiance_random_sigma"] = (dims, np.broadcast_to(random_sigma, rad.shape), {"units": units})
    if systematic_sigma is not None:
        data["sphere_radiance_systematic_sigma"] = (dims, np.broadcast_to(systematic_sigma, rad.shape),
                                                    {"units": units})
    if times is not None:
        data["frame_time"] = ("frame", np.array(times, dtype=str))
    ds = xr.Dataset(data, coords={"band": ["G"], "zenith": ("zenith", z, {"units": "degree"}),
                                  "azimuth": ("azimuth", a, {"units": "degree"})}, attrs={"medium": medium})
    ds.drop_vars(list(drop)).to_netcdf(path)
    return path


def linear_truth(A, B):
    """E_d ... Q of L = A + B cos z in closed form (mu = cos z: int_0^1 (A + B mu) mu dmu = A/2 + B/3, ...)."""
    c = np.cos(np.radians(CONE_DEG))
    t = {"E_d": 2 * np.pi * (A / 2 + B / 3), "E_u": 2 * np.pi * (A / 2 - B / 3),
         "E_0d": 2 * np.pi * (A + B / 2), "E_0u": 2 * np.pi * (A - B / 2),
         "L_d": A + B * (1 + c) / 2, "L_u": A - B * (1 + c) / 2}
    return _ratios(t)


def exp_truth(C, k):
    """The same for L = C exp(k cos z)."""
    c = np.cos(np.radians(CONE_DEG))
    t = {"E_d": 2 * np.pi * C * (np.exp(k) * (k - 1) + 1) / k ** 2,
         "E_u": 2 * np.pi * C * (1 - np.exp(-k) * (1 + k)) / k ** 2,
         "E_0d": 2 * np.pi * C * (np.exp(k) - 1) / k, "E_0u": 2 * np.pi * C * (1 - np.exp(-k)) / k,
         "L_d": C * (np.exp(k) - np.exp(k * c)) / (k * (1 - c)),
         "L_u": C * (np.exp(-k * c) - np.exp(-k)) / (k * (1 - c))}
    return _ratios(t)


def _ratios(t):
    t["E_0"] = t["E_0d"] + t["E_0u"]
    t["mu_d"], t["mu_u"] = t["E_d"] / t["E_0d"], t["E_u"] / t["E_0u"]
    t["mu"] = (t["E_d"] - t["E_u"]) / t["E_0"]
    t["Q"] = t["E_u"] / t["L_u"]
    return t


def exp_field(zenith_deg, azimuth_deg, C=0.02, k=2.5, eps=0.2):
    z, a = np.radians(zenith_deg), np.radians(azimuth_deg)
    return C * np.exp(k * np.cos(z)) * (1 + eps * np.sin(z) * np.cos(a))


def test_linear_and_exponential_fields_integrate_to_the_analytic_values(tmp_path):
    z, a = centres()
    Z, A_ = np.meshgrid(z, a, indexing="ij")
    linear = 1.0 + 0.8 * np.cos(np.radians(Z))
    expo = exp_field(Z, A_)
    ds = compute_light_field([write_grid(tmp_path / "lin.nc", linear), write_grid(tmp_path / "exp.nc", expo)])
    for f, truth in enumerate((linear_truth(1.0, 0.8), exp_truth(0.02, 2.5))):
        for q, value in truth.items():
            got = float(ds[q][f, 0])
            err = float(ds[f"{q}_quadrature_error"][f, 0])
            assert abs(got - value) <= err, (f, q, got, value, err)
            # the stated error is small enough to mean something: within 1 % of the value at 2 degrees
            assert err <= 1e-2 * abs(value), (f, q, err, value)
            # no noise, no fill, no attitude: the quadrature error is all the stated uncertainty
            assert float(ds[f"{q}_sigma"][f, 0]) == pytest.approx(err, rel=1e-12)
    assert "none given" in ds.attrs["attitude"]
    assert ds["E_d"].attrs["standard_name"] == "downwelling_spectral_radiative_flux_in_sea_water"


def _tilted_plane_irradiance(tilt_rad, C=0.02, k=2.5):
    """Reference: the irradiance on a plane tilted by tilt_rad under L = C exp(k cos z), the azimuth integral of
    max(cos z cos b + sin z sin b cos phi, 0) in closed form and the zenith integral by scipy.integrate.quad."""
    def inner(z):
        A, B = np.cos(z) * np.cos(tilt_rad), abs(np.sin(z) * np.sin(tilt_rad))
        if abs(A) >= abs(B):
            ang = 2 * np.pi * A if A > 0 else 0.0
        else:
            phi0 = np.arccos(-A / B)
            ang = 2 * (A * phi0 + B * np.sin(phi0))
        return C * np.exp(k * np.cos(z)) * ang * np.sin(z)
    return integrate.quad(inner, 0, np.pi, limit=200, points=[np.pi / 2 - tilt_rad, np.pi / 2 + tilt_rad])[0]


def test_tilted_field_with_its_attitude_log_recovers_the_untilted_quantities(tmp_path):
    from scipy.spatial.transform import Rotation

    roll, pitch, heading = 0.0, 8.0, 40.0
    z, a = centres()
    Z, A_ = np.meshgrid(np.radians(z), np.radians(a), indexing="ij")
    # camera (forward, right, down) components of each cell centre, to the earth (north, east, down) frame
    cam = np.stack([np.sin(Z) * np.cos(A_), np.sin(Z) * np.sin(A_), -np.cos(Z)], axis=-1)
    earth = Rotation.from_euler("ZYX", [heading, pitch, roll], degrees=True).apply(cam.reshape(-1, 3))
    ze = np.degrees(np.arccos(np.clip(-earth[:, 2], -1, 1))).reshape(Z.shape)
    ae = np.degrees(np.arctan2(earth[:, 1], earth[:, 0])).reshape(Z.shape) % 360
    frame_time = "2026-03-18T16:30:00"
    grid = write_grid(tmp_path / "tilted.nc", exp_field(ze, ae, eps=0.0), times=[frame_time])
    log = tmp_path / "imu.csv"
    sigma = 1.0
    pd.DataFrame({"time_utc": ["2026-03-18T16:29:00Z", "2026-03-18T16:31:00Z"],
                  "roll_deg": [roll, roll], "pitch_deg": [pitch - 1, pitch + 1], "heading_deg": [heading] * 2,
                  "roll_sigma_deg": [0.0, 0.0], "pitch_sigma_deg": [sigma, sigma],
                  "heading_sigma_deg": [2.0, 2.0]}).to_csv(log, index=False)
    ds = compute_light_field([grid], attitude_path=log)
    assert float(ds["pitch_deg"][0]) == pytest.approx(pitch)     # interpolated to the frame's time
    level = compute_light_field([grid])
    truth = exp_truth(0.02, 2.5)
    for q, value in truth.items():
        got, err = float(ds[q][0, 0]), float(ds[f"{q}_quadrature_error"][0, 0])
        assert abs(got - value) <= err, (q, got, value, err)
    # the tilt matters: taken as level, E_d misses by far more than the quadrature error
    assert abs(float(level["E_d"][0, 0]) - truth["E_d"]) > 10 * float(level["E_d_quadrature_error"][0, 0])
    # attitude uncertainty: a pitch error x makes the camera's E_d that of a collector tilted by x from the
    # vertical; the reference's derivatives at x = 0 by steps of 1 degree (the first vanishes, the field being
    # symmetric about the vertical: the second-order term carries it)
    e = [_tilted_plane_irradiance(np.radians(x)) for x in (-1.0, 0.0, 1.0)]
    d1, d2 = (e[2] - e[0]) / 2, e[2] - 2 * e[1] + e[0]          # per degree, per degree^2
    reference = np.sqrt(d1 ** 2 * sigma ** 2 + d2 ** 2 * sigma ** 4 / 2)
    assert float(ds["E_d_attitude_sigma"][0, 0]) == pytest.approx(reference, rel=0.05)


def test_band_between_the_lenses_is_filled_within_its_stated_model_uncertainty(tmp_path):
    z, a = centres()
    Z, A_ = np.meshgrid(z, a, indexing="ij")
    truth_map = exp_field(Z, A_)
    masked = truth_map.copy()
    # the band no lens calibrates in water, and a cap about the zenith with no pixel (filled across the pole)
    gap = ((Z > 70) & (Z < 110)) | (Z < 6)
    masked[gap] = np.nan
    ds = compute_light_field([write_grid(tmp_path / "gap.nc", masked)])
    flag = ds["sphere_cell_flag"][0, 0].values
    assert np.array_equal(flag == 1, gap) and not (flag == 2).any()
    filled = ds["sphere_radiance"][0, 0].values[gap]
    model = ds["sphere_radiance_fill_model_sigma"][0, 0].values[gap]
    err = np.abs(filled - truth_map[gap])
    assert (err <= model).all(), float((err / model).max())
    assert np.median(err / model) > 0.1            # the stated sigma is not vacuous
    truth = exp_truth(0.02, 2.5)
    for q in ("E_d", "E_u", "E_0d", "E_0u", "E_0", "mu_d", "mu_u", "mu", "L_d", "L_u"):
        got, sigma = float(ds[q][0, 0]), float(ds[f"{q}_sigma"][0, 0])
        assert abs(got - truth[q]) <= sigma, (q, got, truth[q], sigma)
    assert 0.05 < float(ds["E_0d_filled_fraction"][0, 0]) < 0.5
    assert float(ds["E_0u_filled_variance_fraction"][0, 0]) > 0.5
    assert float(ds["L_d_filled_fraction"][0, 0]) > 0.5 and float(ds["L_u_filled_fraction"][0, 0]) == 0.0


def test_band_common_scale_cancels_in_average_cosines_and_q_but_not_in_irradiances(tmp_path):
    z, a = centres()
    Z, A_ = np.meshgrid(z, a, indexing="ij")
    rad = exp_field(Z, A_)
    rad[(Z > 80) & (Z < 100)] = np.nan
    ds = compute_light_field([write_grid(tmp_path / "sys.nc", rad, systematic_sigma=0.1 * rad)])
    for q in ("E_d", "E_u", "E_0d", "E_0", "L_d", "L_u"):
        assert float(ds[f"{q}_systematic_sigma"][0, 0]) == pytest.approx(0.1 * float(ds[q][0, 0]), rel=1e-9)
    for q in ("mu_d", "mu_u", "mu", "Q"):
        assert float(ds[f"{q}_systematic_sigma"][0, 0]) < 1e-12 * abs(float(ds[q][0, 0])), q


def test_random_cell_noise_averages_down_as_stated(tmp_path):
    """200 frames of one field, each cell with independent Gaussian noise of the stated sigma (2 % of L), the
    band between the lenses empty: the spread of each quantity over the frames against its stated random
    sigma. The sample standard deviation of 200 draws scatters by 1/sqrt(2 * 199) = 5.0 %: tolerance 4 of
    those, 20 %."""
    grid_deg, n = 6.0, 200
    z, a = centres(grid_deg)
    Z, A_ = np.meshgrid(z, a, indexing="ij")
    rad = exp_field(Z, A_)
    sigma = 0.02 * rad
    noisy = rad + sigma * np.random.default_rng(3).standard_normal((n,) + rad.shape)
    noisy[:, (Z > 70) & (Z < 110)] = np.nan
    ds = compute_light_field([write_grid(tmp_path / "noise.nc", noisy, grid_deg, random_sigma=sigma)])
    for q in ("E_d", "E_u", "E_0", "mu_d", "mu_u", "mu", "L_u", "Q"):
        spread = float(ds[q][:, 0].std(ddof=1))
        stated = float(ds[f"{q}_random_sigma"][:, 0].mean())
        assert spread / stated == pytest.approx(1.0, abs=0.20), (q, spread, stated)


@pytest.mark.parametrize("case, expected", [
    ("missing", "lacks the variable 'sphere_radiance'"),
    ("units", "not spectral radiance"),
    ("outside", "is outside the attitude log"),
    ("columns", "lacks the column(s) pitch_sigma_deg"),
])
def test_bad_input_one_line(tmp_path, capsys, case, expected):
    z, a = centres()
    rad = np.ones((z.size, a.size))
    grid = write_grid(tmp_path / "g.nc", rad, times=["2026-03-18T16:30:00"],
                      units="W m-2 nm-1" if case == "units" else UNITS)
    if case == "missing":
        xr.Dataset({"radiance": (("zenith", "azimuth"), rad)}).to_netcdf(tmp_path / "m.nc")
        grid = tmp_path / "m.nc"
    log = tmp_path / "imu.csv"
    table = pd.DataFrame({"time_utc": ["2026-03-18T17:00:00Z", "2026-03-18T17:10:00Z"], "roll_deg": [0, 0],
                          "pitch_deg": [0, 0], "heading_deg": [0, 0], "roll_sigma_deg": [0.1, 0.1],
                          "pitch_sigma_deg": [0.1, 0.1], "heading_sigma_deg": [1, 1]})
    if case == "columns":
        table = table.drop(columns="pitch_sigma_deg")
    table.to_csv(log, index=False)
    args = ["lightfield", str(grid), "-o", str(tmp_path / "out.nc")]
    if case in ("outside", "columns"):
        args += ["--attitude", str(log)]
    assert main(args) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and expected in err[0] and "Traceback" not in err[0], err
    assert not (tmp_path / "out.nc").exists()


def test_command_writes_a_file_xarray_opens(tmp_path, capsys):
    z, a = centres()
    rad = exp_field(*np.meshgrid(z, a, indexing="ij"))
    grid = write_grid(tmp_path / "g.nc", 1e6 * rad, units="uW m-2 sr-1 nm-1", medium="air")
    out = tmp_path / "lf.nc"
    assert main(["lightfield", str(grid), "-o", str(out)]) == 0
    with xr.open_dataset(out) as ds:
        assert ds["E_d"].attrs["units"] == "W m-2 nm-1"
        assert ds["E_d"].attrs["standard_name"] == "downwelling_spectral_radiative_flux_in_air"
        assert float(ds["E_d"][0, 0]) == pytest.approx(exp_truth(0.02, 2.5)["E_d"], rel=5e-3)
    assert main(["lightfield", str(grid), "-o", str(out)]) == 1       # exists: refused without --overwrite
