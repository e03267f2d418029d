//! PNG chunks written by hand, for files no encoder writes: headers that declare what the file
//! does not hold, and chunks encoders leave out.

/// One PNG chunk: its length, `kind` (four letters), `data` and their CRC-32.
pub fn png_chunk(kind: &[u8], data: &[u8]) -> Vec<u8> {
    let body = [kind, data].concat();
    let mut crc = !0u32;
    for &b in &body {
        crc ^= u32::from(b);
        for _ in 0..8 {
            crc = (crc >> 1) ^ (0xEDB8_8320 & (crc & 1).wrapping_neg());
        }
    }
    [
        &(data.len() as u32).to_be_bytes()[..],
        &body,
        &(!crc).to_be_bytes(),
    ]
    .concat()
}
