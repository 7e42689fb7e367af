"""Vehicle parameters from YAML, and clear errors for bad files."""

import copy

import numpy as np
import pytest
import yaml

from gpg.quadrotor.vehicle import Vehicle, known_vehicles, load_vehicle, vehicle_config


@pytest.fixture(scope="module")
def cfg():
    return vehicle_config("sui_endurance")


def test_loads_public_numbers(vehicle):
    assert vehicle.rotor.n_blades == 2
    np.testing.assert_allclose(vehicle.rotor.radius, 0.1905)
    np.testing.assert_allclose(vehicle.weight, 2.72 * 9.81)
    # X layout, hubs 0.36 m from the centre: l_x = l_y = 0.255 m; r1 rear-right ... r4 front-right.
    p = np.asarray(vehicle.positions)
    np.testing.assert_allclose(np.hypot(p[:, 0], p[:, 1]), 0.36)
    assert np.all(np.sign(p[:, :2]) == [[-1, 1], [-1, -1], [1, -1], [1, 1]])
    spin = np.asarray(vehicle.spin)
    assert spin[0] == spin[2] and spin[1] == spin[3] and spin[0] == -spin[1]
    np.testing.assert_allclose(np.linalg.norm(vehicle.mic_positions, axis=1), 20 * 0.1905)


def test_unknown_vehicle_lists_known():
    with pytest.raises(ValueError, match="known vehicles: .*sui_endurance"):
        load_vehicle("no_such_quad")


@pytest.mark.parametrize(
    "edit, match",
    [
        (lambda c: c.pop("mass"), r"vehicle.mass is missing"),
        (lambda c: c.update(colour="red"), r"vehicle has unknown keys \['colour'\]"),
        (lambda c: c["rotor"].update(radius=-0.1), r"vehicle.rotor.radius must be > 0"),
        (lambda c: c["layout"].update(spin=[1, 1, 0, -1]), r"vehicle.layout.spin"),
        (lambda c: c["rotor"].update(chord_in=[1.0, 2.0]), r"twist_deg and chord_in"),
        (
            lambda c: c["airfoil"].update(lift_slope="fast"),
            r"vehicle.airfoil.lift_slope must be a finite number",
        ),
        (lambda c: c["motor"].update(rpm_min=8000.0), r"rpm_min < rpm_max"),
        (lambda c: c["rotor"].update(hub_height_mm=5), r"vehicle.rotor has unknown keys"),
        (lambda c: c["layout"].update(positions=[[0, 0, 0]] * 4), r"either arm .* or positions"),
        (lambda c: c["motor"].update(time_constant=-1.0), r"time_constant must be >= 0"),
        (lambda c: c.pop("rotor"), r"microphones are placed in rotor radii"),
    ],
)
def test_bad_vehicle_config(cfg, edit, match):
    bad = copy.deepcopy(cfg)
    edit(bad)
    with pytest.raises(ValueError, match=match):
        Vehicle.from_config(bad)


def test_minimal_vehicle_file_loads_and_the_generator_refuses_it():
    """What M and flight need, nothing more: the generator names what it would lack."""
    from gpg.quadrotor.generator import Generator

    v = load_vehicle("minimal_example")
    assert v.rotor is None and v.mic_positions is None and v.air_density is None
    assert float(v.mass) == 0.5 and float(v.gravity) == 9.81
    np.testing.assert_allclose(np.hypot(*np.asarray(v.positions)[:, :2].T), 0.17)
    assert float(v.thrust_coefficient) == 6.1e-8 and float(v.torque_coefficient) == 9.0e-10
    assert v.generator_missing == (
        "rotor",
        "airfoil",
        "microphones",
        "drag_area",
        "air_density",
        "speed_of_sound",
    )
    with pytest.raises(ValueError, match=r"cannot drive the built-in generator: it lacks rotor"):
        Generator(v)


def test_any_path_loads(cfg, tmp_path):
    """load_vehicle reads a file at any path, whatever its suffix; explicit hub positions."""
    mini = {
        "name": "tiny",
        "mass": 0.3,
        "inertia": [1e-3, 1e-3, 2e-3],
        "layout": {
            "positions": [[-0.1, 0.1, 0], [-0.1, -0.1, 0], [0.1, -0.1, 0], [0.1, 0.1, 0]],
            "spin": [1, -1, 1, -1],
        },
        "motor": {"rpm_min": 0, "rpm_max": 12000},
    }
    path = tmp_path / "tiny.vehicle"
    path.write_text(yaml.safe_dump(mini))
    v = load_vehicle(path)
    assert v.name == "tiny" and float(v.motor_time_constant) == 0.0
    assert v.thrust_coefficient is None
    (tmp_path / "broken.yaml").write_bytes(b"\xff\xfe: [")
    with pytest.raises(ValueError, match="is not valid YAML"):
        load_vehicle(tmp_path / "broken.yaml")


def test_shipped_vehicles_are_found_by_name_and_paths_are_not_names(tmp_path):
    assert {"sui_endurance", "minimal_example"} <= set(known_vehicles())
    with pytest.raises(ValueError, match="known vehicles: \\[.*'sui_endurance'"):
        load_vehicle("no_such_vehicle")
    # A path that is not a file is not taken for the name of a shipped vehicle.
    with pytest.raises(ValueError, match="no vehicle file"):
        load_vehicle(tmp_path / "sui_endurance")


def test_half_turn_asymmetries_name_the_rotors_and_microphones(cfg):
    """The shipped vehicle is its own image under the half turn (hubs and spins); its
    microphones on the side are not (the one below is), and a moved hub or a swapped spin is
    named."""
    v = Vehicle.from_config(cfg)
    assert v.half_turn_asymmetries() == []
    mics = v.half_turn_asymmetries(levels=True)
    assert len(mics) == 2 and "microphone 0" in mics[0] and "microphone 1" in mics[1]
    spun = copy.deepcopy(cfg)
    spun["layout"]["spin"] = [1, -1, -1, 1]
    assert Vehicle.from_config(spun).half_turn_asymmetries() == [
        "rotors r1 and r3 spin opposite ways", "rotors r2 and r4 spin opposite ways"]  # fmt: skip
    moved = copy.deepcopy(cfg)
    p = np.asarray(v.positions).tolist()
    p[2][0] += 0.01  # r3 a centimetre forward
    moved["layout"].pop("arm")
    moved["layout"]["positions"] = p
    bad = Vehicle.from_config(moved).half_turn_asymmetries()
    assert len(bad) == 1 and bad[0].startswith("hub r3 ") and "image of r1" in bad[0]
