"""lensfun's vignetting data for the simulated camera: the ``pa`` entries of a lensfun XML database.

:func:`find_lensfun_vignetting` picks a lens by part of its name (and focal length, aperture, distance);
:meth:`radiometry.simulation.vignetting.VignettingSpec.lensfun` turns the entry into a vignetting field
(lensfun's ``r = 1`` is the half-diagonal, as in the simulator).
"""

from __future__ import annotations

import logging
import math
import os
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

from radiometry.errors import CalibrationFileError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class LensfunVignetting:
    """One ``<vignetting model="pa">`` entry of the lensfun database."""

    maker: str
    model: str
    focal: float
    aperture: float
    distance: float
    k1: float
    k2: float
    k3: float
    file: str

    def describe(self) -> str:
        name = self.model if self.model.lower().startswith(self.maker.lower()) else f"{self.maker} {self.model}"
        return f"lensfun {name} @ {self.focal:g} mm f/{self.aperture:g}"

    def corner(self) -> float:
        """``V`` at r = 1 (the corner of a centred image)."""
        return 1.0 + self.k1 + self.k2 + self.k3


def default_lensfun_db() -> Path | None:
    """Where the lensfun XML database is: ``$RADIOMAP_LENSFUN_DB``, ``../shared/data/lensfun/db``
    beside a source checkout, or the system's lensfun data folder; None if none exists."""
    candidates = []
    if os.environ.get("RADIOMAP_LENSFUN_DB"):
        candidates.append(Path(os.environ["RADIOMAP_LENSFUN_DB"]))
    repo = Path(__file__).resolve().parents[2]
    candidates += [repo.parent / "shared" / "data" / "lensfun" / "db",
                   Path("/usr/share/lensfun/version_1"), Path("/usr/share/lensfun")]
    for c in candidates:
        if c.is_dir() and any(c.glob("*.xml")):
            return c
    return None


@lru_cache(maxsize=4)
def _lensfun_entries(db: str) -> tuple[LensfunVignetting, ...]:
    path = Path(db)
    files = sorted(path.glob("*.xml")) if path.is_dir() else [path]
    out: list[LensfunVignetting] = []
    for xml in files:
        try:
            root = ET.parse(xml).getroot()
        except (ET.ParseError, OSError) as exc:
            raise CalibrationFileError(f"{xml}: not a readable lensfun XML file ({exc}); check the database") from None
        for lens in root.iter("lens"):
            maker = next((e.text or "" for e in lens.findall("maker") if "lang" not in e.attrib), "")
            model = next((e.text or "" for e in lens.findall("model") if "lang" not in e.attrib), "")
            for calib in lens.findall("calibration"):
                for v in calib.findall("vignetting"):
                    if v.get("model") != "pa":
                        continue
                    try:
                        out.append(LensfunVignetting(
                            maker.strip(), model.strip(), float(v.get("focal", "nan")),
                            float(v.get("aperture", "nan")), float(v.get("distance", "inf")),
                            float(v.get("k1", 0)), float(v.get("k2", 0)), float(v.get("k3", 0)), xml.name))
                    except ValueError as exc:
                        raise CalibrationFileError(f"{xml}: a vignetting entry of {model!r} has a bad number "
                                                   f"({exc}); check the database") from None
    return tuple(out)


def lensfun_vignetting_entries(db: str | os.PathLike | None = None) -> list[LensfunVignetting]:
    """All ``pa`` vignetting entries of a lensfun database folder (or one XML file)."""
    if db is None:
        db = default_lensfun_db()
        if db is None:
            raise CalibrationFileError("no lensfun database found; pass db=<folder of lensfun *.xml> or set "
                                       "RADIOMAP_LENSFUN_DB")
    db = Path(db)
    if not db.exists():
        raise CalibrationFileError(f"{db}: no such lensfun database; pass the folder holding the *.xml files")
    return list(_lensfun_entries(str(db.resolve())))


def find_lensfun_vignetting(lens: str, *, focal: float | None = None, aperture: float | None = None,
                            distance: float | None = None,
                            db: str | os.PathLike | None = None) -> LensfunVignetting:
    """The entry of the lens whose name contains ``lens`` (case-insensitive, maker + model), nearest to
    ``focal`` (mm), then ``aperture`` (f-number), then ``distance``; without them the widest aperture
    at the shortest focal length (the strongest vignetting of that lens). Several lenses matching is
    fine when they are the same model; otherwise the first in sorted order is used and logged."""
    if not lens or not isinstance(lens, str):
        raise ValueError(f"lens must be a non-empty part of a lens name, got {lens!r}")
    needle = lens.lower()
    entries = [e for e in lensfun_vignetting_entries(db) if needle in f"{e.maker} {e.model}".lower()]
    if not entries:
        raise ValueError(f"no lensfun lens with vignetting data matches {lens!r}; try a shorter part of the "
                         "name, e.g. 'EF-S 18-55'")
    models = sorted({(e.maker, e.model) for e in entries})
    if len(models) > 1:
        log.info("%d lenses match %r; using %s %s", len(models), lens, *models[0])
    entries = [e for e in entries if (e.maker, e.model) == models[0]]

    def key(e: LensfunVignetting) -> tuple[float, float, float]:
        kf = abs(e.focal - focal) if focal is not None else e.focal
        ka = abs(e.aperture - aperture) if aperture is not None else e.aperture
        kd = abs(math.log(max(e.distance, 1e-3)) - math.log(distance)) if distance is not None else 0.0
        return (kf, ka, kd)

    return min(entries, key=key)


__all__ = ["LensfunVignetting", "default_lensfun_db", "find_lensfun_vignetting", "lensfun_vignetting_entries"]
