//! Datasets: insert/get/list/paginate/delete and content pieces.

use super::{count_rows, new_dataset};
use crate::store::{PageRequest, Store, StoreError};

async fn insert_then_get_round_trips_every_field_and_the_content(store: Store) {
    let inserted = store
        .insert_dataset_at(new_dataset("d1"), 1_234)
        .await
        .unwrap();
    let fetched = store
        .get_dataset("d1")
        .await
        .unwrap()
        .expect("dataset exists");
    assert_eq!(fetched, inserted);
    assert_eq!(fetched.display_name, "Dataset d1");
    assert_eq!(fetched.source, "upload");
    assert_eq!(fetched.format, "telemetry-csv");
    assert_eq!(
        (
            fetched.rows,
            fetched.vehicles,
            fetched.labelled_rows,
            fetched.spoofed_rows
        ),
        (10, 2, 8, 3)
    );
    // The two pieces come back in order, and the size is their total.
    let content = vec![b"vehicle_id,timestamp_s\n".to_vec(), b"v1,0.0\n".to_vec()];
    assert_eq!(fetched.size_bytes, 30);
    assert_eq!(fetched.sha256, "sha-d1");
    assert_eq!(fetched.created_at_ms, 1_234);
    assert_eq!(store.dataset_content("d1").await.unwrap(), Some(content));
}

async fn unknown_dataset_reads_as_none_and_deletes_as_not_found(store: Store) {
    assert_eq!(store.get_dataset("nope").await.unwrap(), None);
    assert_eq!(store.dataset_content("nope").await.unwrap(), None);
    let error = store.delete_dataset("nope").await.unwrap_err();
    assert!(
        matches!(&error, StoreError::NotFound { kind: "dataset", id } if id == "nope"),
        "{error:?}"
    );
}

async fn duplicate_dataset_id_is_refused(store: Store) {
    store.insert_dataset(new_dataset("d1")).await.unwrap();
    let error = store.insert_dataset(new_dataset("d1")).await.unwrap_err();
    assert!(
        matches!(&error, StoreError::AlreadyExists { kind: "dataset", id } if id == "d1"),
        "{error:?}"
    );
    assert_eq!(count_rows(&store, "datasets").await, 1);
    assert_eq!(count_rows(&store, "dataset_pieces").await, 2);
}

async fn negative_counts_are_refused_before_touching_the_database(store: Store) {
    let mut dataset = new_dataset("d1");
    dataset.spoofed_rows = -1;
    let error = store.insert_dataset(dataset).await.unwrap_err();
    assert!(
        matches!(
            error,
            StoreError::InvalidValue {
                field: "spoofed_rows",
                ..
            }
        ),
        "{error:?}"
    );
    assert_eq!(count_rows(&store, "datasets").await, 0);
}

async fn list_datasets_pages_newest_first(store: Store) {
    for (id, created_at) in [("a", 10), ("b", 30), ("c", 20)] {
        store
            .insert_dataset_at(new_dataset(id), created_at)
            .await
            .unwrap();
    }
    let first = store.list_datasets(&PageRequest::first(2)).await.unwrap();
    let ids: Vec<_> = first.items.iter().map(|d| d.id.as_str()).collect();
    assert_eq!(ids, ["b", "c"]);
    let token = first.next_page_token.expect("a third dataset follows");
    let second = store
        .list_datasets(&PageRequest::after(2, token))
        .await
        .unwrap();
    let ids: Vec<_> = second.items.iter().map(|d| d.id.as_str()).collect();
    assert_eq!(ids, ["a"]);
    assert_eq!(second.next_page_token, None);

    let error = store
        .list_datasets(&PageRequest::after(2, "zz"))
        .await
        .unwrap_err();
    assert!(matches!(error, StoreError::InvalidPageToken), "{error:?}");
}

async fn deleting_a_dataset_cascades_to_its_content(store: Store) {
    for id in ["a", "b"] {
        store.insert_dataset(new_dataset(id)).await.unwrap();
    }
    store.delete_dataset("a").await.unwrap();
    assert_eq!(store.get_dataset("a").await.unwrap(), None);
    assert_eq!(store.dataset_content("a").await.unwrap(), None);
    assert_eq!(count_rows(&store, "dataset_pieces").await, 2);
    assert!(store.dataset_content("b").await.unwrap().is_some());
}

on_both_backends!(
    insert_then_get_round_trips_every_field_and_the_content,
    unknown_dataset_reads_as_none_and_deletes_as_not_found,
    duplicate_dataset_id_is_refused,
    negative_counts_are_refused_before_touching_the_database,
    list_datasets_pages_newest_first,
    deleting_a_dataset_cascades_to_its_content,
);

/// Migration 0007 on a dataset stored before it: its content reads back whole, as its one piece.
mod datasets_before_version_7_are_one_piece {
    use crate::store::Store;

    const OLD_DATASET: &str = "INSERT INTO datasets (id, display_name, source, format, rows, \
         vehicles, labelled_rows, spoofed_rows, size_bytes, sha256, created_at) \
         VALUES ('old', 'Old', 'upload', 'telemetry', 1, 1, 0, 0, 7, 'sha', 1)";
    /// `v1,0.0\n` as each database writes a blob literal.
    const OLD_CONTENT_SQLITE: &str =
        "INSERT INTO dataset_contents (dataset_id, content) VALUES ('old', X'76312c302e300a')";
    const OLD_CONTENT_POSTGRES: &str = "INSERT INTO dataset_contents (dataset_id, content) \
         VALUES ('old', decode('76312c302e300a', 'hex'))";

    async fn check(store: Store) {
        let content = store.dataset_content("old").await.unwrap();
        assert_eq!(content, Some(vec![b"v1,0.0\n".to_vec()]));
        store.delete_dataset("old").await.unwrap();
        assert_eq!(store.dataset_content("old").await.unwrap(), None);
    }

    from_schema_version!(
        6,
        sqlite: [OLD_DATASET, OLD_CONTENT_SQLITE],
        postgres: [OLD_DATASET, OLD_CONTENT_POSTGRES],
    );
}
