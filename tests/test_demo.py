"""``make demo``'s data: the bundled demo campaign is what the issue asks and is reproducible.

The full demo (a campaign of nine tests, ~8 minutes) is run by ``make demo``, not here;
its campaign machinery is exercised by tests/test_campaign.py on a smaller folder.
"""

from cpas_bayes.data.bundle import read_bundle
from cpas_bayes.app.campaign import configuration_of, folder_digest
from cpas_bayes.app.demo import DEMO_CONFIG, DEMO_TESTS, write_demo_bundles


def test_the_demo_campaign_has_six_drogue_and_three_main_tests_one_hiding_an_effect(tmp_path):
    folder = write_demo_bundles(tmp_path / "a", echo=lambda m: None)
    tests = [read_bundle(folder / name) for name, *_ in DEMO_TESTS]
    configs = [configuration_of(t) for t in tests]
    assert configs.count("2xdrogue-2st") >= 6 and configs.count("3xmain-3st") >= 3
    assert sum(effect != "none" for _, _, effect, _, _ in DEMO_TESTS) == 1
    assert DEMO_CONFIG.diagnose != "off"


def test_the_demo_bundles_are_the_same_bytes_on_every_machine(tmp_path):
    a = write_demo_bundles(tmp_path / "a", echo=lambda m: None)
    b = write_demo_bundles(tmp_path / "b", echo=lambda m: None)
    for name, *_ in DEMO_TESTS:
        assert folder_digest(a / name) == folder_digest(b / name), name
