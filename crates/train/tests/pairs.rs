//! Pair sampling (spec section 11): same-video training pairs drawn as a pure function of
//! (seed, step), epochs that visit every target once, cross-identity pairs, the first-frame
//! protocol of validation, and a threaded loader that delivers exactly the synchronous batches.

use std::collections::{BTreeMap, HashSet};
use std::sync::Arc;

use gagavatar_data::names::video_of;
use gagavatar_data::Dataset;
use gagavatar_train::pairs::{eval_pairs, Loader, PairSampler, SampleSource};
use gagavatar_train::trainer::load_flame;

mod run_common;
use run_common::{init, scratch, synth_dataset};

fn names(videos: &[(&str, usize)]) -> Vec<String> {
    videos
        .iter()
        .flat_map(|(v, n)| (0..*n).map(move |i| format!("{v}_{i}")))
        .collect()
}

#[test]
fn training_pairs_are_same_video_deterministic_and_cover_each_epoch() {
    let train = names(&[("a", 3), ("b", 4), ("c", 1), ("id_x", 5)]);
    let (s, single) = PairSampler::new(&train, 7, 3, 0.0).unwrap();
    assert_eq!(single, 1, "video c has one frame");
    assert_eq!(s.len(), 12, "3 + 4 + 5 targets");
    let (again, _) = PairSampler::new(&train, 7, 3, 0.0).unwrap();
    let mut seen = Vec::new();
    // 4 steps x 3 = 12 samples: exactly one epoch.
    for step in 0..4 {
        let pairs = s.pairs(step);
        assert_eq!(
            pairs,
            again.pairs(step),
            "step {step}: not a function of (seed, step)"
        );
        for p in pairs {
            assert_ne!(p.source, p.target, "step {step}: source == target");
            assert_eq!(
                video_of(&p.source),
                video_of(&p.target),
                "step {step}: {p:?}"
            );
            assert_ne!(
                video_of(&p.target),
                "c",
                "a single-frame video formed a pair"
            );
            seen.push(p.target);
        }
    }
    let distinct: HashSet<&String> = seen.iter().collect();
    assert_eq!(
        distinct.len(),
        12,
        "one epoch visits every target once: {seen:?}"
    );
    // Out-of-order queries give the same answer (the epoch cache must not leak state).
    assert_eq!(s.pairs(9), again.pairs(9));
    assert_eq!(s.pairs(2), again.pairs(2));
    let (other_seed, _) = PairSampler::new(&train, 8, 3, 0.0).unwrap();
    assert_ne!(
        (0..4).map(|k| s.pairs(k)).collect::<Vec<_>>(),
        (0..4).map(|k| other_seed.pairs(k)).collect::<Vec<_>>(),
        "the seed changes the draw"
    );
    // Sources are spread over the other frames of the video.
    let mut sources: BTreeMap<String, HashSet<String>> = BTreeMap::new();
    for step in 0..400 {
        for p in s.pairs(step) {
            sources.entry(p.target).or_default().insert(p.source);
        }
    }
    assert_eq!(sources["id_x_0"].len(), 4, "{:?}", sources["id_x_0"]);
}

#[test]
fn cross_identity_pairs_come_from_other_videos() {
    let train = names(&[("a", 3), ("b", 4), ("c", 2)]);
    let (s, _) = PairSampler::new(&train, 1, 4, 1.0).unwrap();
    for step in 0..20 {
        for p in s.pairs(step) {
            assert_ne!(video_of(&p.source), video_of(&p.target), "{p:?}");
        }
    }
    let (half, _) = PairSampler::new(&train, 1, 4, 0.5).unwrap();
    let cross = (0..100)
        .flat_map(|k| half.pairs(k))
        .filter(|p| video_of(&p.source) != video_of(&p.target))
        .count();
    assert!(
        (150..250).contains(&cross),
        "{cross} of 400 cross pairs at p = 0.5"
    );
    let err = PairSampler::new(&names(&[("a", 3)]), 1, 1, 0.5).unwrap_err();
    assert!(err.to_string().contains("two or more videos"), "{err}");
    let err = PairSampler::new(&names(&[("a", 1), ("b", 1)]), 1, 1, 0.0).unwrap_err();
    assert!(
        err.to_string().contains("no video with two or more frames"),
        "{err}"
    );
}

#[test]
fn evaluation_pairs_use_the_first_frame_of_each_video() {
    // Listed out of natural order: the source is still the first frame in natural order.
    let split: Vec<String> = ["v_10", "v_2", "v_3", "w_0", "w_1", "solo_4"]
        .map(String::from)
        .to_vec();
    let pairs = eval_pairs(&split, None);
    let got: Vec<(&str, &str)> = pairs
        .iter()
        .map(|p| (p.source.as_str(), p.target.as_str()))
        .collect();
    assert_eq!(got, [("v_2", "v_10"), ("v_2", "v_3"), ("w_0", "w_1")]);
    assert_eq!(eval_pairs(&split, Some(2)).len(), 2);
}

#[test]
fn threaded_loader_delivers_the_synchronous_batches_in_order() {
    init();
    let dir = scratch("pairs_loader");
    let data = synth_dataset(&dir, 3, 4, 32, 5);
    let dataset = Dataset::open(&data).unwrap();
    let (sampler, _) = PairSampler::new(&dataset.splits().train, 3, 2, 0.0).unwrap();
    let source = Arc::new(SampleSource::new(
        Arc::new(dataset),
        Arc::new(load_flame(None).unwrap()),
        64,
    ));
    let sampler = Arc::new(sampler);
    let mut sync = Loader::start(source.clone(), sampler.clone(), 5, 12, 0, 1);
    let mut threaded = Loader::start(source, sampler, 5, 12, 3, 2);
    for step in 5..12 {
        let a = sync.next_batch().unwrap();
        let b = threaded.next_batch().unwrap();
        assert_eq!((a.step, b.step), (step, step));
        assert_eq!(a.samples.len(), 2);
        for (x, y) in a.samples.iter().zip(&b.samples) {
            assert_eq!(x.pair, y.pair, "step {step}");
            assert_eq!(x.source_image, y.source_image, "step {step}");
            assert_eq!(x.target_vertices, y.target_vertices, "step {step}");
            // 32 px images are resized to the model's 64.
            assert_eq!(x.target_image.len(), 3 * 64 * 64);
        }
    }
    assert!(threaded.next_batch().is_err(), "past the end");
}

/// A data-parallel rank's share: the ranks' pairs, in rank order, are the one-process batch
/// (cross-identity sources included); a batch that does not split is refused.
#[test]
fn shards_concatenate_to_the_whole_batch() {
    let train = names(&[("a", 3), ("b", 4), ("id_x", 5)]);
    let (whole, _) = PairSampler::new(&train, 5, 6, 0.3).unwrap();
    for size in [1, 2, 3, 6] {
        let shards: Vec<PairSampler> = (0..size)
            .map(|r| {
                let (mut s, _) = PairSampler::new(&train, 5, 6, 0.3).unwrap();
                s.shard(r, size).unwrap();
                assert_eq!(s.share(), (r * 6 / size, 6 / size));
                s
            })
            .collect();
        for step in [0, 1, 7, 40] {
            let joined: Vec<_> = shards.iter().flat_map(|s| s.pairs(step)).collect();
            assert_eq!(joined, whole.pairs(step), "{size} ranks, step {step}");
        }
    }
    let (mut s, _) = PairSampler::new(&train, 5, 6, 0.3).unwrap();
    for (rank, size) in [(0, 4), (0, 0), (2, 2)] {
        let e = s.shard(rank, size).unwrap_err().to_string();
        assert!(e.contains("does not split"), "{e}");
    }
}
