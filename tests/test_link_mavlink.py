"""The link layer's MAVLink codec against pymavlink."""

from __future__ import annotations

from hil.link.mavlink import decode_frame, mav


def test_named_value_int_decodes_to_pymavlinks_message():
    ref = mav.MAVLink(None, srcSystem=1, srcComponent=1)
    for name, value in ((b"mocap_n", 123), (b"abcdefghij", -5), (b"", 0)):
        frame = bytes(ref.named_value_int_encode(1234, name, value).pack(ref))
        mine, theirs = decode_frame(frame), ref.decode(bytearray(frame))
        assert mine.to_dict() == theirs.to_dict() and mine.get_msgbuf() == theirs.get_msgbuf()
