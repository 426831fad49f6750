"""The FDM printer and print settings used to turn ribbons into G-code (mm, mm/s, deg C).

Defaults follow the seed (section 5.5): an Ultimaker 2 (223 x 223 mm bed, 2.85 mm
filament) with a 0.8 mm nozzle printing TPU 95A at 15 mm/s onto fabric held in a frame
on the bed. Coordinates: a pattern point (x, y) in printed-state mm is printed at bed
position (x + origin[0], y + origin[1]) (front side; the back side is mirrored, see
:mod:`geometry.gcode`); the nozzle height is measured from the fabric
top, which sits ``bed_offset_z_mm`` above the bed (0 when the nozzle is calibrated to
start directly above the fabric, as in the seed).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

from geometry.schema import PRINTER_NUMBERS, check_keys, number
from shellfem.errors import SelfshapeError


def _number(name, value):
    """A printer field strictly checked against its physical range (geometry.schema.PRINTER_NUMBERS):
    G-code goes to real hardware, so no value is accepted on type alone."""
    return number(value, f"printer.{name}", PRINTER_NUMBERS[name])


def _pair(name, value):
    if isinstance(value, (str, bytes, dict)):
        raise SelfshapeError(f"printer.{name} must be a pair [x, y], got {value!r:.40}")
    try:
        a, b = value
    except (TypeError, ValueError):
        raise SelfshapeError(f"printer.{name} must be a pair [x, y], got {value!r:.40}") from None
    spec = PRINTER_NUMBERS[name]
    return (number(a, f"printer.{name}[0]", spec), number(b, f"printer.{name}[1]", spec))


@dataclass
class Printer:
    """Printer geometry and print settings (lengths mm, speeds mm/s, temperatures deg C).

    bed_size: printable (x, y) extent of the bed. origin: bed position of the pattern's
    (0, 0); None = centre the bounding box of the ribbons on the bed. layer_height_mm: every layer, the first one too. retraction_mm /
    retraction_speed_mm_s / z_hop_mm: applied on every travel longer than
    ``retract_min_travel_mm``. extrusion_multiplier scales the bead volume (flow).
    mirror_axis_x: bed x of the line the frame is flipped about to print the back side;
    None = the bed centre (the frame base is centred on the bed).
    """
    bed_size: tuple = (223.0, 223.0)
    nozzle_mm: float = 0.8
    filament_diameter_mm: float = 2.85
    layer_height_mm: float = 0.2
    print_speed_mm_s: float = 15.0
    travel_speed_mm_s: float = 100.0
    z_speed_mm_s: float = 10.0
    retraction_mm: float = 4.5
    retraction_speed_mm_s: float = 25.0
    retract_min_travel_mm: float = 1.0
    z_hop_mm: float = 0.5
    extrusion_multiplier: float = 1.0
    nozzle_temperature_c: float = 225.0
    bed_temperature_c: float = 0.0
    bed_offset_z_mm: float = 0.0
    origin: tuple | None = None
    mirror_axis_x: float | None = None
    relative_e: bool = True

    def __post_init__(self):
        """Every field against its range in geometry.schema.PRINTER_NUMBERS (bools and strings
        are never numbers), then the relations: layer height <= nozzle (the bead model needs
        h <= w and a bead is at least a nozzle wide), mirror axis on the bed, origin within one
        bed size of the bed (an origin of 1900 mm on a 223 mm bed was refused only after the
        design, ribbon by ribbon)."""
        self.bed_size = _pair("bed_size", self.bed_size)
        if self.origin is not None:
            self.origin = _pair("origin", self.origin)
        for name in ("nozzle_mm", "filament_diameter_mm", "layer_height_mm", "print_speed_mm_s",
                     "travel_speed_mm_s", "z_speed_mm_s", "retraction_speed_mm_s", "extrusion_multiplier",
                     "retraction_mm", "retract_min_travel_mm", "z_hop_mm", "bed_offset_z_mm",
                     "nozzle_temperature_c", "bed_temperature_c"):
            setattr(self, name, _number(name, getattr(self, name)))
        if self.layer_height_mm > self.nozzle_mm:
            raise SelfshapeError(f"printer.layer_height_mm ({self.layer_height_mm:g}) must not exceed "
                                 f"the nozzle diameter ({self.nozzle_mm:g})")
        if self.mirror_axis_x is not None:
            self.mirror_axis_x = _number("mirror_axis_x", self.mirror_axis_x)
            if self.mirror_axis_x > self.bed_size[0]:
                raise SelfshapeError(f"printer.mirror_axis_x ({self.mirror_axis_x:g}) must lie on the bed, "
                                     f"0..{self.bed_size[0]:g} mm (bed_size[0])")
        if self.origin is not None:
            for i, (o, b) in enumerate(zip(self.origin, self.bed_size)):
                if not -b <= o <= 2.0 * b:       # no pattern at (0, 0) +- one bed can then be printed
                    raise SelfshapeError(f"printer.origin[{i}] ({o:g}) must lie within one bed size of the bed, "
                                         f"{-b:g}..{2 * b:g} mm (bed_size[{i}] = {b:g}): the pattern's (0, 0) goes "
                                         f"there")
        if not isinstance(self.relative_e, bool):
            raise SelfshapeError(f"printer.relative_e must be true or false, got {self.relative_e!r:.40}")

    @property
    def filament_area_mm2(self) -> float:
        """Cross-section of the filament, mm^2."""
        return math.pi * self.filament_diameter_mm ** 2 / 4.0

    @property
    def flip_axis_x(self) -> float:
        """Bed x of the frame's flip line (``mirror_axis_x`` or the bed centre), mm."""
        return self.bed_size[0] / 2.0 if self.mirror_axis_x is None else self.mirror_axis_x


def load_printer(path: str) -> Printer:
    """A :class:`Printer` from a TOML file: its keys are Printer's field names (mm, mm/s,
    deg C), either at the top level or under ``[printer]`` (then nothing else may be beside
    it); missing keys keep the defaults, unknown keys are one-line errors naming the closest
    field, every value is checked against its range (geometry.schema.PRINTER_NUMBERS).

        [printer]
        bed_size = [300, 300]
        nozzle_mm = 0.6
        print_speed_mm_s = 20
    """
    import dataclasses

    from geometry.tomlfile import read_toml
    raw = read_toml(path, f"printer file {path}")
    if not raw:         # an empty or truncated file would print for the default machine
        raise SelfshapeError(f"printer file {path}: no printer keys (an empty file); give at least bed_size, or "
                             f"leave out --printer for the default printer")
    table = raw.get("printer", raw)
    if not isinstance(table, dict):
        raise SelfshapeError(f"printer file {path}: [printer] must be a table")
    known = {f.name for f in dataclasses.fields(Printer)}
    if "printer" in raw:       # keys beside [printer] would be silently ignored
        check_keys(raw, {"printer"}, f"printer file {path}")
        where = f"printer file {path}: [printer]"
    else:
        where = f"printer file {path}"
    check_keys(table, known, where)
    try:
        return Printer(**table)
    except SelfshapeError as e:
        raise SelfshapeError(f"printer file {path}: {e}") from None
