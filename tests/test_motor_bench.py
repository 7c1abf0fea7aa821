"""benchmarks/motor.py --quick: what it writes (every scenario for both stray_field
settings, the price table) and two figures that could come out wrong: the motor's false
wrench falls with distance, and estimating the gradient leaves K A's noise gain alone."""

from __future__ import annotations

import re

from .conftest import benchmark


def test_the_quick_motor_benchmark_reports_every_scenario_and_its_price(tmp_path):
    benchmark("accuracy")  # motor.py takes the sweep and Table II from its sibling
    bench = benchmark("motor")
    out = tmp_path / "figures.md"
    assert bench.main(["--quick", "--out", str(out)]) == 0
    text = out.read_text()
    number = r"([\d.e+-]+)"
    rows = {}
    for stray in ("uniform", "gradient"):
        for scenario, distance in (("on after tare", 15), ("on after tare", 25), ("tared on", 15),
                                   ("100 g, tared on", 15)):
            found = re.search(rf"\| 11 \| linear, {stray} \| {scenario} \| {distance} cm \| "
                              + r" \| ".join([number] * 6) + r" \| .* \| (\d+) of 4 \| (\d+) of (\d+) \| ok \|", text)
            assert found, (stray, scenario, distance)
            rows[stray, scenario, distance] = [float(x) for x in found.groups()]
            assert int(found.group(9)) > 0  # holds' samples were read
    # A dipole's gradient falls as 1/r^4: at 25 cm (0.6^4 = 0.13 of 15 cm's) the false torque is smaller.
    for stray in ("uniform", "gradient"):
        assert max(rows[stray, "on after tare", 25][3:5]) < 0.5 * max(rows[stray, "on after tare", 15][3:5])
    price = dict(re.findall(r"\| 11 \| (uniform|gradient) \| ([\d.e+-]+) \| ", text))
    assert set(price) == {"uniform", "gradient"}
    # The gradient's two directions lie outside the load's: sigma_max(K A) moves under 1 %.
    assert abs(float(price["gradient"]) / float(price["uniform"]) - 1) < 0.01
