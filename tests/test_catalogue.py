"""The effect catalogue's entries: the powers their components name, and what an entry may hold."""
import pytest

from dfxcorr.catalogue import CATALOGUE, Effect, effect


def test_components_name_the_powers_of_x_and_of_the_row_coordinate():
    assert effect("curvature").powers == (2,) and effect("curvature").row_powers == (0,)
    assert effect("visibility_tilt").powers == (1, 2)
    toy = Effect("toy", "phase", True, ("x^0 y^1", "x^2 y^3", "x^1"), 0.0, "shift", "toy")
    assert toy.powers == (0, 2, 1) and toy.row_powers == (1, 3, 0)


@pytest.mark.parametrize("name", [n for n, e in CATALOGUE.items() if not e.per_frame])
def test_a_global_entry_names_a_basis_not_powers(name):
    """Its components ('1', 'x', 'y' of the background) are a basis: no power of x or y is read from them."""
    e = effect(name)
    assert e.powers == (0,) * e.size and e.row_powers == (0,) * e.size


def test_only_the_phase_and_visibility_channels_take_a_row_term():
    with pytest.raises(ValueError, match="powers of y"):
        Effect("toy", "dose", True, ("x^0 y^1",), 1.0, "scale", "toy")
    assert Effect("toy", "visibility", True, ("x^0 y^2",), 0.0, "shift", "toy").row_powers == (2,)
