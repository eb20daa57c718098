"""Sign-in in headless Chromium against the real service: the form shown instead of a page without a valid
token, the token kept in sessionStorage only (no cookie, no localStorage) and sent as ``Authorization:
Bearer``, sign-out, the ``#token=`` sign-in link that leaves no token in the URL, and a revoked token.
"""

from __future__ import annotations

import re
import uuid
from typing import Any

import httpx
import pytest

from tests.browser.support import ARTIFACTS, PageWatch, sign_in_by_link

pytestmark = pytest.mark.browser

TOKEN_KEY = "fotoskhema.token"  # web/lib.js
STORED_TOKEN_JS = f"() => window.sessionStorage.getItem({TOKEN_KEY!r})"


def _assert_token_only_in_session_storage(page: Any, token: str | None) -> None:
    assert page.evaluate(STORED_TOKEN_JS) == token
    assert page.context.cookies() == [], "the viewer set a cookie"
    assert page.evaluate("() => document.cookie") == ""
    assert page.evaluate("() => window.localStorage.length") == 0, "the viewer wrote to localStorage"


def _new_user(live_service: Any, prefix: str) -> tuple[str, str]:
    """(name, token) of a new user, made by the admin through the API."""
    name = f"{prefix}-{uuid.uuid4().hex[:8]}"
    made = httpx.post(f"{live_service.url}/api/users", json={"name": name}, headers=live_service.headers, timeout=10)
    assert made.status_code == 201, made.text
    return name, made.json()["token"]


def test_form_wrong_token_right_token_and_sign_out(watched_page: tuple[Any, PageWatch], live_service: Any) -> None:
    from playwright.sync_api import expect

    page, watch = watched_page
    page.goto(f"{live_service.url}/")
    form = page.get_by_test_id("sign-in-form")
    expect(form).to_be_visible()
    expect(page.get_by_test_id("sign-in-reason")).to_have_text("Sign in with your API token to use Fotoskhema.")
    expect(page.get_by_test_id("token-input")).to_have_attribute("type", "password")
    expect(page.get_by_test_id("token-input")).to_be_focused()
    expect(page.get_by_role("heading", name="Flights", exact=True)).to_have_count(0)  # the form, not the page
    expect(page.get_by_test_id("sign-in-open")).to_be_visible()
    expect(page).to_have_title("Sign in · Fotoskhema")
    ARTIFACTS.mkdir(exist_ok=True)
    page.screenshot(path=str(ARTIFACTS / "sign_in_form.png"), full_page=True)

    page.get_by_test_id("token-input").fill("fsk_not-a-real-token")
    page.get_by_test_id("sign-in-submit").click()
    expect(page.get_by_test_id("sign-in-error")).to_contain_text("That token was not accepted")
    expect(form).to_be_visible()
    _assert_token_only_in_session_storage(page, None)
    page.screenshot(path=str(ARTIFACTS / "sign_in_refused.png"), full_page=True)

    page.get_by_test_id("token-input").fill(live_service.token)
    with page.expect_request(re.compile(r"/api/flights$")) as listing:
        page.get_by_test_id("sign-in-submit").click()
    assert listing.value.headers.get("authorization") == f"Bearer {live_service.token}"
    expect(page.get_by_role("heading", name="Flights", exact=True)).to_be_visible()
    expect(form).to_have_count(0)
    expect(page.get_by_test_id("signed-in-as")).to_have_text("Signed in as admin")
    expect(page.get_by_test_id("user-name")).to_have_text("admin")
    expect(page.locator(".card-body").first).not_to_contain_text("Loading flights")
    _assert_token_only_in_session_storage(page, live_service.token)
    page.screenshot(path=str(ARTIFACTS / "signed_in.png"), full_page=True)

    page.reload()  # the tab keeps its sign-in
    expect(page.get_by_test_id("signed-in-as")).to_have_text("Signed in as admin")
    expect(page.get_by_role("heading", name="Flights", exact=True)).to_be_visible()

    page.get_by_test_id("sign-out").click()
    expect(form).to_be_visible()
    expect(page.get_by_test_id("sign-in-reason")).to_have_text("You are signed out.")
    expect(page.get_by_test_id("signed-in-as")).to_have_count(0)
    expect(page.get_by_test_id("sign-in-open")).to_be_visible()
    _assert_token_only_in_session_storage(page, None)
    page.reload()  # signed out for good: the first request is answered 401 again
    expect(form).to_be_visible()

    page.wait_for_load_state("networkidle")
    # The 401s asked for here: the first page without a token, the wrong token, the page after sign-out.
    watch.forget("/api/me")
    watch.forget("/api/flights")
    watch.assert_clean(live_service.url)


def test_sign_in_link_leaves_no_token_in_the_url(watched_page: tuple[Any, PageWatch], live_service: Any) -> None:
    from playwright.sync_api import expect

    page, watch = watched_page
    token = live_service.token
    page.goto(f"{live_service.url}/#token={token}")
    expect(page.get_by_role("heading", name="Flights", exact=True)).to_be_visible()
    expect(page.get_by_test_id("signed-in-as")).to_have_text("Signed in as admin")
    assert page.evaluate("() => window.location.href") == f"{live_service.url}/#/"
    _assert_token_only_in_session_storage(page, token)

    # A link with another token asks before it replaces the one in use: declined, nothing changes ...
    name, other = _new_user(live_service, "linked")
    questions: list[str] = []
    page.once("dialog", lambda dialog: (questions.append(dialog.message), dialog.dismiss()))
    page.goto(f"{live_service.url}/#/crack-surveys?token={other}")
    expect(page.get_by_role("heading", name="Crack surveys", exact=True)).to_be_visible()
    expect(page.get_by_test_id("user-name")).to_have_text("admin")
    assert questions and "another user" in questions[0]
    _assert_token_only_in_session_storage(page, token)
    # ... accepted, a link to a page, opened in the same tab (no reload), signs in the other user.
    page.goto(f"{live_service.url}/#/")
    page.once("dialog", lambda dialog: dialog.accept())
    page.goto(f"{live_service.url}/#/crack-surveys?token={other}")
    expect(page.get_by_role("heading", name="Crack surveys", exact=True)).to_be_visible()
    expect(page.get_by_test_id("user-name")).to_have_text(name)
    assert page.evaluate("() => window.location.href") == f"{live_service.url}/#/crack-surveys"
    _assert_token_only_in_session_storage(page, other)
    page.go_back()  # the entry the link made was replaced: no token in the history either
    assert token not in page.evaluate("() => window.location.href")
    assert other not in page.evaluate("() => window.location.href")

    page.wait_for_load_state("networkidle")
    leaked = [url for url in watch.request_urls if token in url or other in url]
    assert not leaked, f"a token went into a request URL: {leaked}"
    watch.assert_clean(live_service.url)


def test_revoked_token_shows_the_form_at_the_next_action(
    watched_page: tuple[Any, PageWatch], live_service: Any
) -> None:
    from playwright.sync_api import expect

    page, watch = watched_page
    name, token = _new_user(live_service, "revoked")
    sign_in_by_link(page, live_service.url, token)
    expect(page.get_by_test_id("user-name")).to_have_text(name)
    expect(page.get_by_role("heading", name="Flights", exact=True)).to_be_visible()
    page.wait_for_load_state("networkidle")

    me = httpx.get(f"{live_service.url}/api/me", headers={"Authorization": f"Bearer {token}"}, timeout=10).json()
    (token_id,) = [t["id"] for t in me["tokens"]]
    revoked = httpx.delete(f"{live_service.url}/api/tokens/{token_id}", headers=live_service.headers, timeout=10)
    assert revoked.status_code == 200 and revoked.json()["revoked"] is True, revoked.text

    page.get_by_test_id("nav-crack-surveys").click()
    expect(page.get_by_test_id("sign-in-form")).to_be_visible()
    expect(page.get_by_test_id("sign-in-reason")).to_contain_text("no longer accepted")
    expect(page.get_by_role("heading", name="Crack surveys", exact=True)).to_have_count(0)
    expect(page.get_by_test_id("sign-in-open")).to_be_visible()
    _assert_token_only_in_session_storage(page, None)
    page.screenshot(path=str(ARTIFACTS / "sign_in_revoked.png"), full_page=True)

    # Signing in again (as the admin) goes on to the page that was asked for.
    page.get_by_test_id("token-input").fill(live_service.token)
    page.get_by_test_id("sign-in-submit").click()
    expect(page.get_by_role("heading", name="Crack surveys", exact=True)).to_be_visible()
    expect(page.get_by_test_id("signed-in-as")).to_have_text("Signed in as admin")

    page.wait_for_load_state("networkidle")
    watch.forget("/api/jobs")  # the 401 of the revoked token
    watch.assert_clean(live_service.url)
