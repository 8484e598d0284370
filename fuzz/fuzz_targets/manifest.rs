//! Fuzzes the assembly manifest parser (`aggtool::assembly::Manifest::parse`): any
//! bytes must give a clean `ManifestError` or a manifest whose every instance can be read
//! (asset index in range, a finite, invertible transform) without panicking.
//!
//! ```text
//! aggtool gen forest -o /tmp/f --species 2 --instances 8 --triangles 200   # seeds
//! aggtool gen city -o /tmp/c --instances 10
//! mkdir -p /tmp/corpus/manifest && cp /tmp/f/forest.json /tmp/c/city.json /tmp/corpus/manifest/
//! cd fuzz && RUSTC_BOOTSTRAP=1 cargo fuzz run manifest /tmp/corpus/manifest -- -max_total_time=900 -dict=dict/manifest.dict
//! ```
#![no_main]

use std::path::Path;

use aggtool::assembly::Manifest;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Ok(m) = Manifest::parse(data, Path::new("/fuzz/scene.json")) else {
        return;
    };
    let per_asset = m.instances_per_asset();
    assert_eq!(per_asset.iter().sum::<usize>(), m.instance_count());
    for i in 0..m.instance_count() {
        assert!(m.asset_of(i) < m.assets.len());
        let t = m.transform(i);
        // The parser promises a finite, non-singular transform for every instance it accepts.
        assert!(t.is_finite(), "instance {i}: non-finite transform accepted");
        assert!(
            t.matrix3.determinant() != 0.0,
            "instance {i}: singular transform accepted"
        );
    }
    let _ = m.instance_bytes();
});
