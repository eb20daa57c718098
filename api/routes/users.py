"""Who am I, and (admins) users and their API tokens. The CLI ``fotoskhema users`` does the same offline."""

from __future__ import annotations

from fastapi import APIRouter, Query, Request

from api.auth import AdminDep, UserDep, token_cache
from api.deps import DbDep, TokenId, UserName
from api.errors import ConflictError, NotFoundError
from api.models import TokenCreated, TokenOut, UserCreate, UserOut
from core import accounts
from core.accounts import AccountError

router = APIRouter(prefix="/api", tags=["users"])


def _user_out(name: str, is_admin: bool, tokens: list[accounts.TokenInfo]) -> UserOut:
    return UserOut(name=name, is_admin=is_admin, tokens=[_token_out(t) for t in tokens])


def _token_out(t: accounts.TokenInfo) -> TokenOut:
    return TokenOut.model_validate(t, from_attributes=True)


@router.get("/me", response_model=UserOut)
def me(principal: UserDep, db: DbDep) -> UserOut:
    """The user of the token sent, with their tokens (never the secrets)."""
    (user,) = accounts.list_users(db, principal.user_id)
    return _user_out(*user)


@router.get("/users", response_model=list[UserOut])
def list_users(_admin: AdminDep, db: DbDep) -> list[UserOut]:
    return [_user_out(*u) for u in accounts.list_users(db)]


@router.post("/users", status_code=201, response_model=TokenCreated)
def create_user(body: UserCreate, _admin: AdminDep, db: DbDep) -> TokenCreated:
    """Make a user; the answer holds their first token, shown this once."""
    try:
        token = accounts.create_user(db, body.name, admin=body.is_admin, label=body.label)
    except AccountError as exc:
        raise ConflictError(str(exc)) from None
    return TokenCreated(user=body.name, token=token)


@router.post("/users/{name}/tokens", status_code=201, response_model=TokenCreated)
def issue_token(name: UserName, _admin: AdminDep, db: DbDep, label: str = Query("", max_length=200)) -> TokenCreated:
    """Another token for a user, shown this once."""
    try:
        return TokenCreated(user=name, token=accounts.issue_token(db, name, label=label))
    except AccountError as exc:
        raise NotFoundError(str(exc)) from None


@router.delete("/tokens/{token_id}", response_model=TokenOut)
def revoke_token(token_id: TokenId, principal: UserDep, db: DbDep, request: Request) -> TokenOut:
    """Revoke a token: your own, or anyone's for an admin. Requests with it answer 401 from then on (in other
    API processes within a few seconds)."""
    try:
        revoked = accounts.revoke_token(db, token_id, by=principal)
    except AccountError as exc:
        raise NotFoundError(str(exc)) from None
    token_cache(request).clear()
    return _token_out(revoked)
