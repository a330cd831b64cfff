//! The cost of the wire codec for one pendulum-sized batch (state 3, goal 2, action 1) of 1024
//! transitions, stage by stage and end to end: `encode_batch_into` (reused message), prost
//! serialisation (reused buffer), prost deserialisation (a fresh message, as tonic does), and
//! the validating `decode_batch` (moves the vectors) or `decode_batch_into` (copies into a reused
//! batch). Throughput is transitions per second on one core; the gRPC ingest target is
//! 1,000,000 transitions/s on 2 cores, so the `round_trip` figure shows how much of that budget
//! the codec takes (the actor pays the encode half, the learner the decode half).

use std::hint::black_box;

use criterion::{BatchSize, Criterion, Throughput, criterion_group, criterion_main};
use hac_core::{Batch, LevelDims};
use hac_proto::{decode_batch, decode_batch_into, encode_batch, encode_batch_into, pb};
use prost::Message;

const LEN: usize = 1024;
const DIMS: [LevelDims; 1] = [LevelDims {
    state: 3,
    goal: 2,
    action: 1,
}];

fn pendulum_batch() -> Batch {
    let mut batch = Batch::zeros(DIMS[0], LEN);
    let fields = [
        &mut batch.states,
        &mut batch.actions,
        &mut batch.rewards,
        &mut batch.next_states,
        &mut batch.goals,
    ];
    for (f, values) in fields.into_iter().enumerate() {
        for (i, v) in values.iter_mut().enumerate() {
            *v = ((i * 7 + f) % 13) as f32 * 0.37 - 2.0;
        }
    }
    for (i, t) in batch.terminals.iter_mut().enumerate() {
        *t = f32::from(u8::from(i % 10 == 9));
    }
    batch
}

fn codec(c: &mut Criterion) {
    let batch = pendulum_batch();
    let msg = encode_batch(0, 1, &batch);
    let bytes = msg.encode_to_vec();

    let mut group = c.benchmark_group("codec_pendulum_1024");
    group.throughput(Throughput::Elements(LEN as u64));

    let mut out = pb::TransitionBatch::default();
    group.bench_function("encode_batch_into", |b| {
        b.iter(|| encode_batch_into(&mut out, 0, 1, black_box(&batch)))
    });

    let mut buf = Vec::with_capacity(bytes.len());
    group.bench_function("prost_encode", |b| {
        b.iter(|| {
            buf.clear();
            black_box(&msg).encode(&mut buf).expect("the buffer grows");
        })
    });

    group.bench_function("prost_decode", |b| {
        b.iter(|| pb::TransitionBatch::decode(black_box(bytes.as_slice())).expect("valid bytes"))
    });

    group.bench_function("decode_batch", |b| {
        b.iter_batched(
            || msg.clone(),
            |m| decode_batch(m, &DIMS, LEN).expect("valid batch"),
            BatchSize::SmallInput,
        )
    });

    let mut decoded = Batch::zeros(DIMS[0], 0);
    group.bench_function("decode_batch_into", |b| {
        b.iter(|| {
            decode_batch_into(black_box(&msg), &DIMS, LEN, &mut decoded).expect("valid batch")
        })
    });

    group.bench_function("round_trip", |b| {
        b.iter(|| {
            encode_batch_into(&mut out, 0, 1, black_box(&batch));
            buf.clear();
            out.encode(&mut buf).expect("the buffer grows");
            let received = pb::TransitionBatch::decode(buf.as_slice()).expect("valid bytes");
            decode_batch(received, &DIMS, LEN).expect("valid batch")
        })
    });
    group.finish();
}

criterion_group!(benches, codec);
criterion_main!(benches);
