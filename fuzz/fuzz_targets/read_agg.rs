//! Fuzzes the `.agg` reader: any bytes must give a clean error or a file every accessor can
//! read without panicking. Checksums are skipped so that mutations reach the structural checks
//! (with them, a mutation is caught by the CRC and nothing deeper runs).
//!
//! ```text
//! cargo install cargo-fuzz
//! cargo +nightly fuzz run read_agg fuzz/corpus/read_agg tests/data -- -max_total_time=300
//! RUSTC_BOOTSTRAP=1 cargo fuzz run read_agg fuzz/corpus/read_agg tests/data   # a stable toolchain
//! ```
//! (`tests/data` seeds it with a file of each format version: 1.0–1.3 floats, 1.4 quantized, 1.5 compressed; more
//! small bakes can go in the corpus, e.g. `aggtool convert x.glb --max-res 8 -o fuzz/corpus/read_agg/x.agg`).
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let _ = aggtool::format::Aggregate::from_bytes(data.to_vec());
    if let Ok(agg) = aggtool::format::Aggregate::from_bytes_ignoring_checksums(data.to_vec()) {
        aggtool::format::exercise(&agg);
    }
});
