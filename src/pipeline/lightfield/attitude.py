"""Camera attitude: roll, pitch and heading from a sidecar log, interpolated to each frame, and the earth frame.

Frames (right-handed, as inertial sensors report them):

- earth: x north, y east, z down (NED);
- camera: x towards the grid's azimuth 0 on the camera's horizon ("forward"),
  y towards azimuth 90 ("right"), z towards the grid's nadir (away from the lens
  that looks at the grid's zenith). The grid's azimuth therefore increases from
  forward to right, clockwise seen from above, as a compass does.

A direction with zenith angle z and azimuth a has components
(sin z cos a, sin z sin a, -cos z) in either frame, and a camera direction d
is the earth direction R d with R = Rz(heading) Ry(pitch) Rx(roll) (the
aerospace z-y-x sequence: positive pitch raises the forward axis, positive roll
lowers the right one, heading from north towards east). With no attitude the
grid's zenith is the zenith and its azimuth 0 is taken as north.

The sidecar is a CSV file with a header and the columns ``time_utc`` (ISO
8601, UTC unless it carries an offset), ``roll_deg``, ``pitch_deg``,
``heading_deg`` and their standard uncertainties ``roll_sigma_deg``,
``pitch_sigma_deg``, ``heading_sigma_deg``. Each frame takes the linear
interpolation of the two samples around its time (heading unwrapped first);
a frame outside the log's span is refused.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.spatial.transform import Rotation

from pipeline.errors import InputError

__all__ = ["ATTITUDE_COLUMNS", "Attitude", "read_attitude", "attitude_at", "rotation", "earth_up_in_camera",
           "camera_to_earth_directions", "solar_position", "LEVEL"]

ATTITUDE_COLUMNS = ("time_utc", "roll_deg", "pitch_deg", "heading_deg", "roll_sigma_deg", "pitch_sigma_deg",
                    "heading_sigma_deg")

#: grid components (sin z cos a, sin z sin a, cos z) -> NED-type components (sin z cos a, sin z sin a, -cos z)
_FLIP = np.diag([1.0, 1.0, -1.0])


@dataclass(frozen=True)
class Attitude:
    """Roll, pitch, heading (deg) and their standard uncertainties (deg) of one frame."""

    roll_deg: float = 0.0
    pitch_deg: float = 0.0
    heading_deg: float = 0.0
    roll_sigma_deg: float = 0.0
    pitch_sigma_deg: float = 0.0
    heading_sigma_deg: float = 0.0


LEVEL = Attitude()


def read_attitude(path) -> pd.DataFrame:
    """The attitude log as a table indexed by UTC time (sorted), its columns checked; bad input: one line.

    Parameters
    ----------
    path : str or pathlib.Path
        The attitude log (CSV with the columns ``ATTITUDE_COLUMNS``, module docstring).

    Returns
    -------
    pandas.DataFrame
        Roll, pitch, heading and their standard uncertainties (degree), indexed by UTC time; ``attrs["path"]`` the
        file.

    Raises
    ------
    InputError
        When the file cannot be read, lacks a column, has no rows, a time that is not ISO 8601, a value that is
        not a number, a negative uncertainty or two rows at one time.
    """
    path = Path(path)
    try:
        table = pd.read_csv(path)
    except (OSError, ValueError, pd.errors.ParserError) as exc:
        raise InputError(path, f"cannot read the attitude log as CSV ({exc.__class__.__name__}: {exc})") from None
    missing = [c for c in ATTITUDE_COLUMNS if c not in table.columns]
    if missing:
        raise InputError(path, f"attitude log lacks the column(s) {', '.join(missing)} "
                         f"(needs {', '.join(ATTITUDE_COLUMNS)})")
    if table.empty:
        raise InputError(path, "attitude log has no rows")
    try:
        times = pd.to_datetime(table["time_utc"], utc=True, format="ISO8601")
    except (ValueError, TypeError) as exc:
        raise InputError(path, f"column 'time_utc' is not ISO 8601 date and time ({exc})") from None
    values = table[list(ATTITUDE_COLUMNS[1:])].apply(pd.to_numeric, errors="coerce")
    bad = values.isna().any(axis=1) | ~np.isfinite(values).all(axis=1)
    if bad.any():
        line = int(np.flatnonzero(bad.to_numpy())[0]) + 2
        raise InputError(path, f"line {line}: roll, pitch, heading and their sigmas must be numbers")
    sigmas = values[["roll_sigma_deg", "pitch_sigma_deg", "heading_sigma_deg"]]
    if (sigmas < 0).any(axis=None):
        line = int(np.flatnonzero((sigmas < 0).any(axis=1).to_numpy())[0]) + 2
        raise InputError(path, f"line {line}: a standard uncertainty is negative")
    out = values.set_index(pd.DatetimeIndex(times, name="time_utc")).sort_index()
    if out.index.has_duplicates:
        raise InputError(path, f"attitude log has two rows at the same time {out.index[out.index.duplicated()][0]}")
    out.attrs["path"] = str(path)
    return out


def attitude_at(log: pd.DataFrame, times_utc: pd.DatetimeIndex, frame_names=None) -> list[Attitude]:
    """Each frame's attitude, linearly interpolated in time (heading unwrapped); outside the log: one line.

    Parameters
    ----------
    log : pandas.DataFrame
        The attitude log (:func:`read_attitude`).
    times_utc : pandas.DatetimeIndex
        The frames' UTC times.
    frame_names : sequence of str, optional
        Names of the frames for the error message; the times when None.

    Returns
    -------
    list of Attitude
        One attitude per frame, degree (heading in [0, 360)), the sigmas interpolated as the angles are.

    Raises
    ------
    InputError
        When a frame's time is outside the log's span.
    """
    t = log.index.as_unit("ns").asi8.astype(float)
    first, last = log.index[0], log.index[-1]
    names = list(frame_names) if frame_names is not None else [str(x) for x in times_utc]
    out = []
    heading = np.degrees(np.unwrap(np.radians(log["heading_deg"].to_numpy())))
    for name, when in zip(names, times_utc):
        if when < first or when > last:
            raise InputError(log.attrs.get('path', 'attitude log'), f"frame {name} at {when.isoformat()} is outside "
                             f"the attitude log ({first.isoformat()} to {last.isoformat()}; a frame time without an "
                             "offset is the camera clock less --camera-utc-offset-h)")
        x = float(pd.Timestamp(when).as_unit("ns").value)

        def at(values, x=x):
            return float(np.interp(x, t, values))
        out.append(Attitude(at(log["roll_deg"].to_numpy()), at(log["pitch_deg"].to_numpy()), at(heading) % 360.0,
                            at(log["roll_sigma_deg"].to_numpy()), at(log["pitch_sigma_deg"].to_numpy()),
                            at(log["heading_sigma_deg"].to_numpy())))
    return out


def rotation(roll_deg: float, pitch_deg: float, heading_deg: float) -> Rotation:
    """Camera (forward, right, down) to earth (north, east, down): Rz(heading) Ry(pitch) Rx(roll).

    Parameters
    ----------
    roll_deg : float
        Roll, degree (positive lowers the right axis).
    pitch_deg : float
        Pitch, degree (positive raises the forward axis).
    heading_deg : float
        Heading, degree from north towards east.

    Returns
    -------
    scipy.spatial.transform.Rotation
        The rotation from camera to earth (NED) components.
    """
    return Rotation.from_euler("ZYX", [heading_deg, pitch_deg, roll_deg], degrees=True)


def earth_up_in_camera(roll_deg: float, pitch_deg: float) -> np.ndarray:
    """The earth's zenith as a unit vector in the grid's components (sin z cos a, sin z sin a, cos z).

    Heading turns about the vertical and leaves it unchanged.

    Parameters
    ----------
    roll_deg : float
        Roll, degree.
    pitch_deg : float
        Pitch, degree.

    Returns
    -------
    numpy.ndarray
        The unit vector of the earth's zenith in the camera's grid components, shape ``(3,)``.
    """
    down_in_camera = rotation(roll_deg, pitch_deg, 0.0).inv().apply([0.0, 0.0, 1.0])
    return _FLIP @ (-down_in_camera)


def camera_to_earth_directions(attitude: Attitude, camera_vectors: np.ndarray) -> np.ndarray:
    """Grid-component unit vectors of camera directions (..., 3) as earth-frame grid components
    (sin z cos a, sin z sin a, cos z) with a from north towards east.

    Parameters
    ----------
    attitude : Attitude
        The frame's roll, pitch and heading, degree.
    camera_vectors : numpy.ndarray
        Unit vectors in the camera's grid components, shape ``(..., 3)``.

    Returns
    -------
    numpy.ndarray
        The same directions in the earth's grid components (azimuth from north towards east), shape ``(..., 3)``.
    """
    r = rotation(attitude.roll_deg, attitude.pitch_deg, attitude.heading_deg)
    flat = camera_vectors.reshape(-1, 3) @ _FLIP
    return (r.apply(flat) @ _FLIP).reshape(camera_vectors.shape)


def earth_to_camera_directions(attitude: Attitude, earth_vectors: np.ndarray) -> np.ndarray:
    """The inverse of :func:`camera_to_earth_directions`.

    Parameters
    ----------
    attitude : Attitude
        The frame's roll, pitch and heading, degree.
    earth_vectors : numpy.ndarray
        Unit vectors in the earth's grid components, shape ``(..., 3)``.

    Returns
    -------
    numpy.ndarray
        The same directions in the camera's grid components, shape ``(..., 3)``.
    """
    r = rotation(attitude.roll_deg, attitude.pitch_deg, attitude.heading_deg)
    flat = earth_vectors.reshape(-1, 3) @ _FLIP
    return (r.inv().apply(flat) @ _FLIP).reshape(earth_vectors.shape)


def solar_position(times_utc: pd.DatetimeIndex, latitude_deg: float, longitude_deg: float,
                   altitude_m: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Apparent solar zenith angle and azimuth (deg, from north towards east) at the frames' times (pvlib).

    Parameters
    ----------
    times_utc : pandas.DatetimeIndex
        The frames' UTC times.
    latitude_deg : float
        Site latitude, degree north.
    longitude_deg : float
        Site longitude, degree east.
    altitude_m : float, default 0.0
        Site altitude, m.

    Returns
    -------
    zenith : numpy.ndarray
        Apparent (refracted) solar zenith angle, degree, one per time.
    azimuth : numpy.ndarray
        Solar azimuth, degree from north towards east, one per time.
    """
    from pvlib.solarposition import get_solarposition

    pos = get_solarposition(times_utc, latitude_deg, longitude_deg, altitude=altitude_m)
    return pos["apparent_zenith"].to_numpy(float), pos["azimuth"].to_numpy(float)
