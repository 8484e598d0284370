//! Criterion benchmark of the assembly manifest's parse: 100,000 instances (the module's
//! "a million instances parse in about a second" at a tenth of the size), streamed into the
//! compact 52-byte-per-instance storage. `cargo bench --bench manifest`.

use std::path::Path;

use aggtool::assembly::Manifest;
use criterion::{criterion_group, criterion_main, Criterion, Throughput};

/// A manifest of `n` instances of two assets, in a grid.
fn manifest(n: usize) -> String {
    let mut s = String::from(
        r#"{"version":1,"assets":{"a":{"source":"a.glb"},"b":{"source":"b.glb"}},"instances":["#,
    );
    for i in 0..n {
        if i > 0 {
            s.push(',');
        }
        s.push_str(&format!(
            r#"{{"asset":"{}","translation":[{},0,{}],"rotation":[0,0,0,1],"scale":[1,1,1]}}"#,
            if i % 3 == 0 { "a" } else { "b" },
            i % 317,
            i / 317
        ));
    }
    s.push_str("]}");
    s
}

fn bench(c: &mut Criterion) {
    let n = 100_000;
    let text = manifest(n);
    let mut g = c.benchmark_group("manifest");
    g.throughput(Throughput::Elements(n as u64));
    g.sample_size(10);
    g.bench_function("parse_100k_instances", |b| {
        b.iter(|| {
            let m = Manifest::parse(text.as_bytes(), Path::new("bench.json")).unwrap();
            assert_eq!(m.instance_count(), n);
            m
        })
    });
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
