"""Per-node keys and the authentication envelope (deploy/contract/keyring.py,
deploy/contract/mac.py): who can make a tag a receiver believes, on the lab graph
(a = [[0,0,0],[1,0,0],[1,1,0]], b = [1,0,0]: agent 3 reads agent 2's replies)."""

from __future__ import annotations

import os

import pytest

from deploy.contract import mac
from deploy.contract.keyring import (
    BAD_MAC,
    UNSIGNED,
    WRONG_SENDER,
    Keyring,
    KeysError,
    keyring_text,
    new_master,
    pair_key,
    read_file,
    write_file,
)
from deploy.contract.scenario import load_scenario
from deploy.contract.wire import Keys, run_roles

FLEET = "k"


@pytest.fixture(scope="module")
def lab():
    return load_scenario("lab")


@pytest.fixture(scope="module")
def rings(lab):
    """Every node's keyring of one run of lab (the launcher's too)."""
    master = new_master()
    roles = [*run_roles(lab.robot_ids), "launcher"]
    return {r: Keyring.from_text(keyring_text(master, FLEET, r, roles), "test", r, lab,
                                 Keys(FLEET)) for r in roles}


def test_pair_keys_are_the_pairs_alone():
    m = new_master()
    assert pair_key(m, FLEET, "agent-2", "plant") == pair_key(m, FLEET, "plant", "agent-2")
    assert pair_key(m, FLEET, "agent-2", "plant") != pair_key(m, FLEET, "agent-3", "plant")
    assert pair_key(m, FLEET, "agent-2", "plant") != pair_key(m, "other", "agent-2", "plant")
    assert pair_key(m, FLEET, "agent-2", "plant") != pair_key(new_master(), FLEET, "agent-2",
                                                             "plant")


def test_a_reply_is_tagged_for_its_receivers_only_and_each_checks_its_own(rings):
    keys = Keys(FLEET)
    key = keys.cmd(2)
    sealed = rings["agent-2"].seal(b"\x93\x01\x02\x03", key)
    # the plant, agent 3 (a_32 != 0) and the launcher get a tag; agent 1 (a_12 = 0) none
    assert sorted(rings["agent-2"].receivers[key]) == ["agent-3", "launcher", "plant"]
    assert len(sealed) == 4 + 3 * mac.ENTRY_BYTES + mac.TRAILER_BYTES
    for r in ("plant", "agent-3", "launcher"):
        payload, why = rings[r].open(sealed, key)
        assert why == "" and bytes(payload) == b"\x93\x01\x02\x03"
    assert rings["agent-1"].open(sealed, key) == (None, BAD_MAC)  # no tag for it
    # the same bytes on another key (robot 3's) do not check: the key is in the tag
    assert rings["plant"].open(sealed, keys.cmd(3))[1] == WRONG_SENDER


def test_a_compromised_agent_cannot_command_another_robot(rings):
    """Agent 3 holds its own keys (with agent 2 too, with the plant too), not agent 2's
    key with the plant: whatever it signs on robot/2/cmd, the plant refuses."""
    keys = Keys(FLEET)
    three = rings["agent-3"]
    payload = b"\x93\x00\x00\x00"
    # as itself: it is not a sender of robot/2/cmd
    assert rings["plant"].open(three.seal(payload, keys.cmd(2)), keys.cmd(2)) == (
        None, WRONG_SENDER)
    # claiming to be agent 2, tagged with every key it holds for the plant and agent 2
    stolen = [
        (mac.hint("plant"), mac.prefixed(three._pair["plant"], keys.cmd(2), "agent-2", "plant")),
        (mac.hint("plant"), mac.prefixed(three._pair["agent-2"], keys.cmd(2), "agent-2",
                                         "plant"))]
    forged = mac.seal(payload, stolen, mac.trailer(mac.hint("agent-2"), len(stolen)))
    assert rings["plant"].open(forged, keys.cmd(2)) == (None, BAD_MAC)
    # its own robot: taken
    assert rings["plant"].open(three.seal(payload, keys.cmd(3)), keys.cmd(3))[1] == ""


def test_control_only_from_the_plant_or_the_launcher(rings):
    keys = Keys(FLEET)
    for sender in ("plant", "launcher"):
        sealed = rings[sender].seal(b"\x91\x00", keys.ctl("stop"))
        for r in ("leader", "agent-1", "agent-2", "agent-3", "plant", "launcher"):
            assert rings[r].open(sealed, keys.ctl("stop"))[1] == "", (sender, r)
    by_agent = rings["agent-1"].seal(b"\x91\x00", keys.ctl("stop"))
    assert rings["plant"].open(by_agent, keys.ctl("stop"))[1] == WRONG_SENDER
    # a key nobody sends on (made up under ctl/*)
    made_up = keys.ctl("made-up")
    assert rings["plant"].open(rings["launcher"].seal(b"\x91\x00", made_up), made_up)[1] == (
        WRONG_SENDER)


def test_what_is_not_an_envelope_or_was_touched_is_refused(rings):
    keys = Keys(FLEET)
    key = keys.sample(2)
    sealed = rings["plant"].seal(b"\x93\x01\x02\x03", key)
    assert rings["agent-2"].open(b"\x93\x01\x02\x03", key) == (None, UNSIGNED)
    assert rings["agent-2"].open(b"", key) == (None, UNSIGNED)
    assert rings["agent-2"].open(sealed[-mac.TRAILER_BYTES:], key) == (None, UNSIGNED)  # no payload
    mine = sealed.index(mac.hint("agent-2"), 4)  # agent 2's entry among the tags
    for at in range(len(sealed) - mac.TRAILER_BYTES):  # every byte of payload and tags
        bad = bytearray(sealed)
        bad[at] ^= 0x01
        opened = rings["agent-2"].open(bytes(bad), key)[0]
        if at < 4 or mine <= at < mine + mac.ENTRY_BYTES:  # the payload, or its own tag
            assert opened is None, at
        else:  # another receiver's tag: not agent 2's business
            assert opened is not None, at
    garbage = os.urandom(300) + bytes((0, 0, 2, mac.MAGIC))
    assert rings["agent-2"].open(garbage, key)[0] is None


def test_a_keyring_file_others_may_read_is_refused(tmp_path, lab):
    text = keyring_text(new_master(), FLEET, "agent-2", run_roles(lab.robot_ids))
    path = write_file(tmp_path / "agent-2.keys", text)
    assert path.stat().st_mode & 0o777 == 0o600
    assert read_file(path) == text.encode()
    path.chmod(0o640)
    with pytest.raises(KeysError, match="chmod 600"):
        read_file(path)
    path.chmod(0o600)
    with pytest.raises(KeysError, match="keys of agent-2, not of agent-3"):
        Keyring.from_text(text, str(path), "agent-3", lab, Keys(FLEET))
    with pytest.raises(KeysError, match="fleet"):
        Keyring.from_text(text, str(path), "agent-2", lab, Keys("other"))
    with pytest.raises(KeysError, match="not a role of scenario"):
        Keyring.from_text(keyring_text(new_master(), FLEET, "agent-2", ["agent-9"]), "x",
                          "agent-2", lab, Keys(FLEET))
    with pytest.raises(KeysError, match="not an omnifleet keyring"):
        Keyring.from_text('{"format": 1}', "x", "agent-2", lab, Keys(FLEET))


def test_an_envelope_holds_a_tag_for_every_receiver_of_a_large_fleet():
    """Control goes to every node of the run: a fleet of 300 robots has 303 receivers."""
    key, payload = "omr/k/ctl/tick", b"\x91\x01"
    starts = [(mac.hint(f"agent-{i}"), mac.prefixed(bytes(32), key, "plant", f"agent-{i}"))
              for i in range(300)]
    sealed = mac.seal(payload, starts, mac.trailer(mac.hint("plant"), len(starts)))
    assert mac.parse_head(sealed) == (len(payload), mac.hint("plant"), 300)
    last = {mac.hint("plant"): [mac.prefixed(bytes(32), key, "plant", "agent-299")]}
    assert mac.open_envelope(sealed, mac.hint("agent-299"), last)[1] == ""


def test_a_receiver_finds_its_tag_wherever_its_hint_bytes_also_appear():
    """The receiver's hint searched in C: bytes equal to it inside another entry's tag
    (or several entries under its hint, as a forger who tags with every key it holds
    writes them) neither hide its own tag nor pass for it."""
    key, payload, me = "omr/k/robot/2/cmd", b"\x93\x01\x02\x03", mac.hint("plant")
    start = mac.prefixed(bytes(range(32)), key, "agent-2", "plant")
    good = start.copy()
    good.update(payload)
    decoy = mac.hint("agent-3") + b"\x00" * 5 + me + b"\x00" * 9  # its tag holds `me`
    wrong = me + b"\x11" * 16  # an entry under my hint that does not check
    trail = mac.trailer(mac.hint("agent-2"), 3)
    senders = {mac.hint("agent-2"): [start]}
    data = payload + decoy + wrong + me + good.digest() + trail
    assert mac.open_envelope(data, me, senders) == (memoryview(payload), "")
    data = payload + decoy + wrong + wrong + trail
    assert mac.open_envelope(data, me, senders) == (None, mac.BAD_MAC)
