"""Find the MLX90393s on a bus and take one reading from each.

Scanning stops whatever the chips were doing (it sends EX and reconfigures
them): do not scan a bus a running daemon is using.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from ftsensord.chip import mlx90393 as mlx
from ftsensord.chip.driver import MLX90393, Measurement
from ftsensord.chip.i2c import Bus
from ftsensord.errors import ChipError, ChipNotRespondingError


@dataclass
class ChipReport:
    """What a scan learnt about one address that answered."""

    address: int
    part: str
    registers: dict[int, int] = field(default_factory=dict)  # CONF1..CONF3 as found
    tref: int | None = None
    measurement: Measurement | None = None
    error: str | None = None

    def as_dict(self) -> dict[str, object]:
        found = mlx.Settings.from_registers(self.registers) if len(self.registers) == 3 else None
        m = self.measurement
        return {
            "address": f"0x{self.address:02X}",
            "part": self.part,
            "registers": {f"0x{r:02X}": f"0x{v:04X}" for r, v in self.registers.items()},
            "found_settings": None
            if found is None
            else {
                "GAIN_SEL": found.gain_sel,
                "HALLCONF": f"0x{found.hallconf:X}",
                "RES_XYZ": [found.res_x, found.res_y, found.res_z],
                "OSR": found.osr,
                "DIG_FILT": found.dig_filt,
                "OSR2": found.osr2,
                "TCMP_EN": int(found.tcmp_en),
                "BURST_SEL": found.burst_sel,
                "BURST_DATA_RATE": found.burst_data_rate,
            },
            "tref": None if self.tref is None else f"0x{self.tref:04X}",
            "field_ut": None if m is None else [round(float(v) * 1e6, 3) for v in m.field_t],
            "saturated": None if m is None else [bool(s) for s in m.saturated],
            "temperature_c": None if m is None or m.temperature_c is None else round(m.temperature_c, 2),
            "error": self.error,
        }


def probe(bus: Bus, address: int) -> bool:
    """True when something ACKs EX at ``address`` (EX is harmless in every mode).

    A chip that answers with ERROR is present, only unwell: `scan` lists it
    with its error instead of hiding it.
    """
    try:
        MLX90393(bus, address, sleep=bus.sleep).exit_mode()
    except ChipNotRespondingError:
        return False
    except ChipError:
        return True
    return True


def scan(
    bus: Bus,
    settings: mlx.Settings = mlx.Settings(),
    addresses: range = range(mlx.ADDRESS_MIN, mlx.ADDRESS_MAX + 1),
) -> list[ChipReport]:
    """Probe ``addresses``; for each chip found, read its registers as found,
    then configure ``settings`` and take one X, Y, Z, T reading."""
    reports = []
    for address in addresses:
        if not probe(bus, address):
            continue
        chip = MLX90393(bus, address, sleep=bus.sleep)
        report = ChipReport(address, mlx.part_variant(address))
        try:
            report.registers = chip.read_configuration()
            report.tref = chip.read_register(mlx.REG_TREF)
            chip.configure(settings)
            report.measurement = chip.measure(mlx.ZYXT_XYZT)
        except ChipError as exc:
            report.error = str(exc)
        reports.append(report)
    return reports


def format_table(reports: list[ChipReport], spec: str) -> str:
    """The reports as the table `ftsensord scan` prints (fields in uT, temperatures in degC)."""
    nan3 = [float("nan")] * 3
    lines = [
        f"{'addr':<5} {'part':<20} {'CONF1':<6} {'CONF2':<6} {'CONF3':<6} "
        f"{'Bx/uT':>9} {'By/uT':>9} {'Bz/uT':>9} {'T/degC':>7}  notes"
    ]
    for r in reports:
        regs = [f"0x{r.registers[i]:04X}" if i in r.registers else "-" for i in range(3)]
        m = r.measurement
        field = nan3 if m is None else [float(v) * 1e6 for v in m.field_t]
        temp = float("nan") if m is None or m.temperature_c is None else m.temperature_c
        notes = []
        if len(r.registers) == 3:
            s = mlx.Settings.from_registers(r.registers)
            notes.append(
                f"found GAIN_SEL={s.gain_sel} RES={s.res_x}{s.res_y}{s.res_z} "
                f"OSR={s.osr} DIG_FILT={s.dig_filt}"
            )
        if m is not None and m.any_saturated:
            notes.append("SATURATED " + "".join(a for a, sat in zip("XYZ", m.saturated) if sat))
        if r.error:
            notes.append(f"ERROR: {r.error}")
        lines.append(
            f"0x{r.address:02X}  {r.part:<20} {regs[0]:<6} {regs[1]:<6} {regs[2]:<6} "
            f"{field[0]:>9.1f} {field[1]:>9.1f} {field[2]:>9.1f} {temp:>7.2f}  " + "; ".join(notes)
        )
    lines.append(f"{len(reports)} chip(s) found on {spec}")
    return "\n".join(lines)
