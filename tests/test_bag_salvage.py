"""Bag salvage: an unfinished or damaged bag is read as far as it is intact, a repaired copy is
written, and the input is never changed."""
import struct

import pytest

from drift_tools.bag import bag_info, read_bag
from drift_tools.bag_salvage import BagDamagedError, recover_bag, scan_bag
from test_tools_bag import T0, encoder, state, write_run


def chunk_offsets(path):
    """Byte offsets of the chunk records, from the file's own chunk index."""
    from mcap.reader import make_reader
    with open(path, 'rb') as fh:
        return [c.chunk_start_offset for c in make_reader(fh).get_summary().chunk_indexes]


def damage(path, offset, new: bytes):
    data = bytearray(path.read_bytes())
    data[offset:offset + len(new)] = new
    path.write_bytes(bytes(data))


def speeds(bag):
    return [m.msg.v for m in read_bag(bag, backend='mcap')['/vehicle/state']]


@pytest.fixture
def bag(tmp_path):
    write_run(tmp_path / 'bag', 400, chunk_size=2048).close()
    return tmp_path / 'bag'


def test_a_whole_bag_scans_complete_and_recovers_identical(bag, tmp_path):
    scan = scan_bag(bag)
    assert scan.complete and scan.problems() == [] and len(scan.messages) == 600
    rec = recover_bag(bag, tmp_path / 'copy')
    assert rec.kept == {'/vehicle/state': 400, '/drift/nmpc/status': 200}
    assert speeds(tmp_path / 'copy') == speeds(bag)
    assert bag_info(tmp_path / 'copy').message_count == 600


@pytest.mark.parametrize('how', ['length', 'crc'])
def test_a_damaged_chunk_in_the_middle_loses_only_that_chunk(bag, tmp_path, how):
    mcap = next(bag.glob('*.mcap'))
    offsets = chunk_offsets(mcap)
    assert len(offsets) > 10
    full = speeds(bag)
    victim = offsets[len(offsets) // 2]
    if how == 'length':          # the chunk header's record length: the walk loses its footing
        damage(mcap, victim + 1, struct.pack('<Q', 2**40))
    else:                        # a byte of its content: the CRC no longer matches
        damage(mcap, victim + 100, b'\xff\xfe')
    before = mcap.read_bytes()
    scan = scan_bag(bag)
    assert len(scan.damage) == 1 and scan.chunks == len(offsets) - 1
    assert scan.finished and not scan.complete
    lost = 600 - len(scan.messages)
    assert 0 < lost < 20                             # a 2 kB chunk holds ~15 messages
    got = speeds(bag)                                # as much as the readers can read
    assert got == sorted(got) and len(got) >= 400 - lost
    rec = recover_bag(bag, tmp_path / 'fixed')
    assert sum(rec.kept.values()) == 600 - lost
    assert any('damaged chunk' in p for p in rec.problems)
    kept = speeds(tmp_path / 'fixed')
    missing = [i for i, v in enumerate(full) if v not in set(kept)]
    assert kept == [v for v in full if v in set(kept)] and missing
    assert missing == list(range(missing[0], missing[-1] + 1)), 'lost more than one stretch'
    assert mcap.read_bytes() == before, 'the input was changed'


def test_channels_lost_with_the_first_chunk_come_back_from_metadata(bag, tmp_path):
    mcap = next(bag.glob('*.mcap'))
    offsets = chunk_offsets(mcap)
    mcap.write_bytes(mcap.read_bytes()[:offsets[-1]])   # unfinished: no summary repeats them
    damage(mcap, offsets[0] + 200, b'\x00\x01\x02\x03')   # the chunk with schemas, channels
    scan = scan_bag(bag)
    assert scan.channels_from_metadata == (1, 2) and scan.orphans == 0
    rec = recover_bag(bag, tmp_path / 'fixed')
    assert rec.kept['/vehicle/state'] > 380
    assert speeds(tmp_path / 'fixed')[-1] > 0.5 * 380


def test_an_unfinished_record_at_the_end_is_reported(tmp_path):
    w = write_run(tmp_path / 'live', 100, chunk_size=10**6, flush_every=50)
    w._stream.write(b'\x06' + struct.pack('<Q', 5000) + b'half a chunk')   # a write cut short
    w._stream.flush()
    scan = scan_bag(tmp_path / 'live')
    assert not scan.finished and [d.what for d in scan.damage] == ['unfinished record']
    assert len(scan.messages) == 150
    w.close()


def test_a_file_cut_inside_a_chunk_keeps_the_whole_records_before_the_cut(tmp_path):
    write_run(tmp_path / 'bag', 400, chunk_size=10**6).close()   # one chunk for everything
    mcap = next((tmp_path / 'bag').glob('*.mcap'))
    offsets = chunk_offsets(mcap)
    assert len(offsets) == 1
    mcap.write_bytes(mcap.read_bytes()[:offsets[0] + 20000])     # a copy cut short
    scan = scan_bag(tmp_path / 'bag')
    assert [d.what for d in scan.damage] == [f'unfinished chunk ({len(scan.messages)} '
                                             'messages of it kept)']
    rec = recover_bag(tmp_path / 'bag', tmp_path / 'fixed')
    kept = speeds(tmp_path / 'fixed')
    assert 20 < len(kept) == rec.kept['/vehicle/state'] < 400
    assert kept == [m.msg.v for m in read_bag(tmp_path / 'bag', backend='mcap')
                    ['/vehicle/state']][:len(kept)]


def test_recover_refuses_a_non_empty_target_and_garbage(bag, tmp_path):
    (tmp_path / 'full').mkdir()
    (tmp_path / 'full' / 'x').write_text('x')
    with pytest.raises(FileExistsError):
        recover_bag(bag, tmp_path / 'full')
    with pytest.raises(FileExistsError):
        recover_bag(bag, bag)
    (tmp_path / 'junk').mkdir()
    (tmp_path / 'junk' / 'junk_0.mcap').write_bytes(b'not an mcap file at all')
    with pytest.raises(BagDamagedError, match='not an MCAP'):
        scan_bag(tmp_path / 'junk')
    with pytest.raises(BagDamagedError, match='no such bag'):
        scan_bag(tmp_path / 'nothing')


def test_garbage_between_chunks_is_skipped(tmp_path):
    w = write_run(tmp_path / 'b', 100, chunk_size=10**6, flush_every=50)
    w._stream.write(bytes(range(256)) * 4)          # a stretch of junk, then more chunks
    enc = encoder('drift_msgs/msg/VehicleState')
    for i in range(100, 120):
        w.write('/vehicle/state', enc(state(i)), T0 + i * 10**7)
    w.close()
    scan = scan_bag(tmp_path / 'b')
    assert [d.what for d in scan.damage] == ['unreadable bytes']
    assert len([m for m in scan.messages if m.channel_id == 1]) == 120


def test_bag_cli_info_and_recover(tmp_path, capsys):
    from drift_tools.operator import main

    class bag_cli:               # scripts/bag.py is `drift bag`
        @staticmethod
        def main(argv):
            return main(['bag', *argv])
    write_run(tmp_path / 'bag', 200, chunk_size=2048).close()
    assert bag_cli.main(['info', str(tmp_path / 'bag')]) == 0
    mcap = next((tmp_path / 'bag').glob('*.mcap'))
    mcap.write_bytes(mcap.read_bytes()[:chunk_offsets(mcap)[-1]])   # as after a SIGKILL
    capsys.readouterr()
    assert bag_cli.main(['info', str(tmp_path / 'bag')]) == 1
    assert 'no footer' in capsys.readouterr().out
    assert bag_cli.main(['recover', str(tmp_path / 'bag'), str(tmp_path / 'fixed')]) == 0
    assert 'kept' in capsys.readouterr().out
    assert bag_cli.main(['info', str(tmp_path / 'fixed')]) == 0
    assert bag_cli.main(['recover', str(tmp_path / 'bag'), str(tmp_path / 'fixed')]) == 2
    assert bag_cli.main(['info', str(tmp_path / 'nope')]) == 2
    err = capsys.readouterr().err
    assert err.count('\n') == 2 and 'Traceback' not in err
