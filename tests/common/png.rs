//! PNG pieces for tests that build or mend PNG files by hand.

/// The CRC-32 of a PNG chunk (its type and data), bit by bit as the PNG
/// specification defines it.
pub fn crc32(bytes: &[u8]) -> u32 {
    let mut c = !0u32;
    for &b in bytes {
        c ^= u32::from(b);
        for _ in 0..8 {
            c = if c & 1 != 0 {
                (c >> 1) ^ 0xEDB8_8320
            } else {
                c >> 1
            };
        }
    }
    !c
}
