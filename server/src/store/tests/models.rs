//! Models: insert/get/list/paginate/delete, artifacts, active-model switching.

use serde_json::json;

use super::{count_rows, new_model};
use crate::store::{BackendKind, ModelSource, PageRequest, Store, StoreError};

async fn insert_then_get_round_trips_every_field_and_the_artifact(store: Store) {
    let mut model = new_model("m1");
    model.source = ModelSource::Bundled;
    model.training_operation = None;
    model.artifact = vec![0, 255, 7, 42, 0];
    let inserted = store
        .insert_model_at(model, 1_700_000_000_123)
        .await
        .unwrap();

    let fetched = store.get_model("m1").await.unwrap().expect("model exists");
    assert_eq!(fetched, inserted);
    assert_eq!(fetched.id, "m1");
    assert_eq!(fetched.display_name, "Model m1");
    assert_eq!(fetched.source, ModelSource::Bundled);
    assert_eq!(fetched.training_operation, None);
    assert_eq!(fetched.created_at_ms, 1_700_000_000_123);
    assert_eq!(fetched.schema_version, 1);
    assert_eq!(fetched.sha256, "sha-m1");
    assert_eq!(fetched.size_bytes, 5);
    assert_eq!(
        fetched.metadata,
        json!({"threshold": 0.5, "auroc": 0.93, "id": "m1"})
    );
    assert!(!fetched.active);
    assert_eq!(
        store.model_artifact("m1").await.unwrap(),
        Some(vec![0, 255, 7, 42, 0])
    );
}

async fn insert_stamps_the_current_time(store: Store) {
    let before = crate::store::now_unix_ms();
    let inserted = store.insert_model(new_model("m1")).await.unwrap();
    let after = crate::store::now_unix_ms();
    assert!((before..=after).contains(&inserted.created_at_ms));
    assert_eq!(store.get_model("m1").await.unwrap(), Some(inserted));
}

async fn unknown_model_reads_as_none(store: Store) {
    assert_eq!(store.get_model("nope").await.unwrap(), None);
    assert_eq!(store.model_artifact("nope").await.unwrap(), None);
    assert_eq!(store.active_model().await.unwrap(), None);
    assert_eq!(store.model_count().await.unwrap(), 0);
}

async fn duplicate_model_id_is_refused_and_keeps_the_original(store: Store) {
    store.insert_model(new_model("m1")).await.unwrap();
    let mut duplicate = new_model("m1");
    duplicate.display_name = "impostor".to_owned();
    duplicate.artifact = vec![9; 10];

    let error = store.insert_model(duplicate).await.unwrap_err();
    assert!(
        matches!(&error, StoreError::AlreadyExists { kind: "model", id } if id == "m1"),
        "{error:?}"
    );
    assert_eq!(error.to_string(), "model 'm1' already exists");
    let kept = store.get_model("m1").await.unwrap().expect("original kept");
    assert_eq!(kept.display_name, "Model m1");
    assert_eq!(
        store.model_artifact("m1").await.unwrap(),
        Some(vec![1, 2, 3])
    );
    assert_eq!(store.model_count().await.unwrap(), 1);
}

async fn list_models_pages_newest_first_with_ties_broken_by_id(store: Store) {
    for (id, created_at) in [("a", 200), ("b", 200), ("c", 300), ("d", 50), ("e", 100)] {
        store
            .insert_model_at(new_model(id), created_at)
            .await
            .unwrap();
    }

    let mut seen = Vec::new();
    let mut pages = 0;
    let mut request = PageRequest::first(2);
    loop {
        let page = store.list_models(&request).await.unwrap();
        pages += 1;
        assert!(page.items.len() <= 2);
        seen.extend(page.items.iter().map(|m| m.id.clone()));
        match page.next_page_token {
            Some(token) => request = PageRequest::after(2, token),
            None => break,
        }
    }
    assert_eq!(seen, ["c", "b", "a", "e", "d"]);
    assert_eq!(pages, 3);

    // An exact fit returns no dangling token.
    let all = store.list_models(&PageRequest::first(5)).await.unwrap();
    assert_eq!(all.items.len(), 5);
    assert_eq!(all.next_page_token, None);
    // Page size 0 means the default.
    assert_eq!(
        store.list_models(&PageRequest::default()).await.unwrap(),
        all
    );
}

async fn keyset_pages_skip_nothing_when_rows_change_between_pages(store: Store) {
    for (id, created_at) in [("a", 100), ("b", 200), ("c", 300)] {
        store
            .insert_model_at(new_model(id), created_at)
            .await
            .unwrap();
    }
    let first = store.list_models(&PageRequest::first(1)).await.unwrap();
    assert_eq!(first.items[0].id, "c");
    // A newer model and the deletion of the last-seen one must not shift the next page.
    store.insert_model_at(new_model("z"), 400).await.unwrap();
    store.delete_model("c").await.unwrap();
    let token = first.next_page_token.expect("more pages");
    let rest = store
        .list_models(&PageRequest::after(10, token))
        .await
        .unwrap();
    let ids: Vec<_> = rest.items.iter().map(|m| m.id.as_str()).collect();
    assert_eq!(ids, ["b", "a"]);
}

async fn invalid_or_foreign_page_tokens_are_refused(store: Store) {
    for id in ["a", "b"] {
        store.insert_model(new_model(id)).await.unwrap();
        store.insert_dataset(super::new_dataset(id)).await.unwrap();
    }
    for token in ["garbage", "0123", "v1|models|1|a"] {
        let error = store
            .list_models(&PageRequest::after(1, token))
            .await
            .unwrap_err();
        assert!(
            matches!(error, StoreError::InvalidPageToken),
            "{token}: {error:?}"
        );
    }
    let dataset_token = store
        .list_datasets(&PageRequest::first(1))
        .await
        .unwrap()
        .next_page_token
        .expect("two datasets, page of one");
    let error = store
        .list_models(&PageRequest::after(1, dataset_token))
        .await
        .unwrap_err();
    assert!(matches!(error, StoreError::InvalidPageToken), "{error:?}");
    // An empty token is the first page, as in gRPC where unset strings are empty.
    let first = store.list_models(&PageRequest::after(1, "")).await.unwrap();
    assert_eq!(first.items.len(), 1);
}

async fn set_active_model_switches_so_exactly_one_is_active(store: Store) {
    for id in ["a", "b", "c"] {
        store.insert_model(new_model(id)).await.unwrap();
    }
    let activated = store.set_active_model("a").await.unwrap();
    assert!(activated.active);
    assert_eq!(activated.id, "a");
    assert_eq!(store.active_model().await.unwrap(), Some(activated));

    let switched = store.set_active_model("b").await.unwrap();
    assert_eq!(switched.id, "b");
    assert_eq!(active_ids(&store).await, ["b"]);
    assert!(!store.get_model("a").await.unwrap().expect("a").active);

    // Re-activating the active model is a no-op that still succeeds.
    assert!(store.set_active_model("b").await.unwrap().active);
    assert_eq!(active_ids(&store).await, ["b"]);

    // An unknown id changes nothing.
    let error = store.set_active_model("nope").await.unwrap_err();
    assert!(
        matches!(&error, StoreError::NotFound { kind: "model", id } if id == "nope"),
        "{error:?}"
    );
    assert_eq!(active_ids(&store).await, ["b"]);
}

async fn schema_forbids_two_active_models_even_for_raw_updates(store: Store) {
    for id in ["a", "b"] {
        store.insert_model(new_model(id)).await.unwrap();
    }
    store.set_active_model("a").await.unwrap();
    let raw = store
        .try_execute_for_test("UPDATE models SET active = TRUE WHERE id = 'b'")
        .await
        .unwrap_err();
    assert!(
        matches!(
            crate::store::error::insert_error(raw, "model", "b"),
            StoreError::AlreadyExists { .. }
        ),
        "a raw second active row must hit the unique index"
    );
    assert_eq!(active_ids(&store).await, ["a"]);
}

async fn deleting_the_active_model_is_refused_and_nothing_is_lost(store: Store) {
    store.insert_model(new_model("a")).await.unwrap();
    store.set_active_model("a").await.unwrap();

    let error = store.delete_model("a").await.unwrap_err();
    assert!(
        matches!(&error, StoreError::ModelActive { id } if id == "a"),
        "{error:?}"
    );
    let kept = store.get_model("a").await.unwrap().expect("still there");
    assert!(kept.active);
    assert_eq!(
        store.model_artifact("a").await.unwrap(),
        Some(vec![1, 2, 3])
    );
    assert_eq!(count_rows(&store, "model_artifacts").await, 1);
}

async fn deleting_a_model_cascades_to_its_artifact(store: Store) {
    for id in ["a", "b"] {
        store.insert_model(new_model(id)).await.unwrap();
    }
    assert_eq!(count_rows(&store, "model_artifacts").await, 2);
    store.delete_model("a").await.unwrap();

    assert_eq!(store.get_model("a").await.unwrap(), None);
    assert_eq!(store.model_artifact("a").await.unwrap(), None);
    assert_eq!(count_rows(&store, "model_artifacts").await, 1);
    assert_eq!(store.model_count().await.unwrap(), 1);
    assert_eq!(
        store.model_artifact("b").await.unwrap(),
        Some(vec![1, 2, 3])
    );

    let error = store.delete_model("a").await.unwrap_err();
    assert!(
        matches!(&error, StoreError::NotFound { kind: "model", id } if id == "a"),
        "{error:?}"
    );
    assert_eq!(error.to_string(), "model 'a' not found");
}

async fn model_count_counts_registered_models(store: Store) {
    for id in ["a", "b", "c"] {
        store.insert_model(new_model(id)).await.unwrap();
    }
    assert_eq!(store.model_count().await.unwrap(), 3);
    store.delete_model("b").await.unwrap();
    assert_eq!(store.model_count().await.unwrap(), 2);
}

/// Ids of every active model, straight from the table.
async fn active_ids(store: &crate::store::Store) -> Vec<String> {
    store
        .strings_for_test("SELECT id FROM models WHERE active ORDER BY id")
        .await
}

/// Makes the activation of the model `poisoned` fail inside the database (a trigger), as a crash or
/// a fault between storing a model and activating it would.
async fn fail_the_activation_of_poisoned(store: &Store) {
    match store.kind() {
        BackendKind::Sqlite => {
            store
                .execute_for_test(
                    "CREATE TRIGGER fail_activation BEFORE UPDATE OF active ON models \
                     WHEN NEW.active AND NEW.id = 'poisoned' \
                     BEGIN SELECT RAISE(ABORT, 'injected failure'); END",
                )
                .await;
        }
        BackendKind::Postgres => {
            store
                .execute_for_test(
                    "CREATE FUNCTION fail_activation() RETURNS trigger AS $$ \
                     BEGIN RAISE EXCEPTION 'injected failure'; END $$ LANGUAGE plpgsql",
                )
                .await;
            store
                .execute_for_test(
                    "CREATE TRIGGER fail_activation BEFORE UPDATE OF active ON models \
                     FOR EACH ROW WHEN (NEW.active AND NEW.id = 'poisoned') \
                     EXECUTE FUNCTION fail_activation()",
                )
                .await;
        }
    }
}

async fn insert_and_activate_is_one_transaction(store: Store) {
    store.insert_model(new_model("old")).await.unwrap();
    store.set_active_model("old").await.unwrap();
    fail_the_activation_of_poisoned(&store).await;

    store
        .insert_active_model(new_model("poisoned"))
        .await
        .expect_err("the injected failure");
    assert_eq!(store.get_model("poisoned").await.unwrap(), None);
    assert_eq!(store.model_artifact("poisoned").await.unwrap(), None);
    assert_eq!(count_rows(&store, "models").await, 1);
    assert_eq!(count_rows(&store, "model_artifacts").await, 1);
    let active = store.active_model().await.unwrap().expect("one is active");
    assert_eq!(active.id, "old", "the previous model stays active");

    let inserted = store.insert_active_model(new_model("new")).await.unwrap();
    assert!(inserted.active);
    assert_eq!(store.get_model("new").await.unwrap(), Some(inserted));
    assert_eq!(
        store.active_model().await.unwrap().expect("active").id,
        "new"
    );
    assert!(!store.get_model("old").await.unwrap().expect("kept").active);
}

on_both_backends!(
    insert_and_activate_is_one_transaction,
    insert_then_get_round_trips_every_field_and_the_artifact,
    insert_stamps_the_current_time,
    unknown_model_reads_as_none,
    duplicate_model_id_is_refused_and_keeps_the_original,
    list_models_pages_newest_first_with_ties_broken_by_id,
    keyset_pages_skip_nothing_when_rows_change_between_pages,
    invalid_or_foreign_page_tokens_are_refused,
    set_active_model_switches_so_exactly_one_is_active,
    schema_forbids_two_active_models_even_for_raw_updates,
    deleting_the_active_model_is_refused_and_nothing_is_lost,
    deleting_a_model_cascades_to_its_artifact,
    model_count_counts_registered_models,
);
