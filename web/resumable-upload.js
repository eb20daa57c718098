/* Resumable upload of one large photo into a flight: the tus 1.0.0 protocol (POST /api/flights/<id>/uploads,
 * then PATCHes) with tus-js-client, vendored at set-up as Leaflet is (the global `tus`, no CDN).
 *
 * The file goes in PATCHes of `chunkBytes`; where the browser can hash (a secure context: https, or
 * localhost) each carries its SHA-256 in Upload-Checksum, so a chunk damaged on the way is refused (460) and
 * sent again. A network error, or an answer the protocol says to retry (409 offset, 423 busy, 460, 5xx), is
 * retried after RETRY_DELAYS_MS from the offset the server holds (HEAD): only the bytes it lacks go again.
 * tus-js-client keeps the upload's URL in localStorage by the file's name, size and date, so a file picked again
 * after a reload (or after the retries ran out) continues where it stopped. Once the last byte is in, the
 * server checks the photo as it checks a multipart one; its answer (or the refusal) is returned here.
 */

import { ApiError, api, authHeaders, detailOf, onAbort, parseJson, reportUnauthorized, storedToken } from "./lib.js";

const DEFAULT_BYTES = 32 * 1024 * 1024; // the server's defaults, if its configuration does not say
export const RETRY_DELAYS_MS = [0, 1000, 3000, 5000, 10000, 20000, 30000]; // then it gives up and says so
const RETRY_STATUSES = new Set([409, 423, 460]); // offset moved, another request writing, damaged chunk

/** `files` split by size: the `large` ones (from the configuration's `resumable_upload_bytes` on; all when it is
 * 0) go by resumable upload, one at a time; the `small` ones in multipart batches. */
export function byUploadKind(files, config) {
  const from = Number(config.resumable_upload_bytes);
  const threshold = Number.isFinite(from) && from >= 0 ? from : DEFAULT_BYTES;
  return { small: files.filter((f) => f.size < threshold), large: files.filter((f) => f.size >= threshold) };
}

/**
 * Send `file` to flight `flightId` by tus; resolves with the photo's metadata (as POST /images answers each),
 * rejects with an ApiError saying why it failed. `onProgress(sentBytes)`, `onRetry(attempt, delayMs)`.
 */
export async function resumableUpload(file, { flightId, chunkBytes, signal, onProgress, onRetry }) {
  const token = storedToken();
  const url = await new Promise((resolve, reject) => {
    const upload = new tus.Upload(file, {
      endpoint: `/api/flights/${flightId}/uploads`,
      chunkSize: Number(chunkBytes) > 0 ? Number(chunkBytes) : DEFAULT_BYTES,
      retryDelays: RETRY_DELAYS_MS,
      metadata: { filename: file.name, filetype: file.type || "application/octet-stream" },
      headers: authHeaders(token),
      removeFingerprintOnSuccess: true,
      httpStack: checksummed(new tus.DefaultHttpStack({})),
      onProgress: (sent) => onProgress(sent),
      onShouldRetry: (error, attempt) => {
        const retry = retryable(error);
        if (retry) onRetry(attempt + 1, RETRY_DELAYS_MS[attempt]);
        return retry;
      },
      onSuccess: () => resolve(upload.url),
      onError: (error) => reject(failure(error, file, token)),
    });
    onAbort(signal, () => {
      upload.abort();
      reject(new ApiError(0, "the upload was stopped"));
    });
    upload.findPreviousUploads().then((previous) => {
      if (previous.length) upload.resumeFromPreviousUpload(previous[0]);
      upload.start();
    }, reject);
  });
  const answer = await api("GET", new URL(url, window.location.href).pathname, { signal });
  return answer.image;
}

/** Whether tus-js-client should try again: no answer at all, a server error, or one of RETRY_STATUSES. */
function retryable(error) {
  const status = error.originalResponse ? error.originalResponse.getStatus() : 0;
  const transient = status === 0 || status >= 500 || RETRY_STATUSES.has(status);
  return transient && navigator.onLine !== false;
}

/** The error a failed upload ends with, with the server's `detail` when it answered. */
function failure(error, file, token) {
  const response = error && error.originalResponse;
  if (!response) {
    return new ApiError(0, `${file.name}: the server could not be reached; choose the file again to continue where it stopped`);
  }
  const status = response.getStatus();
  const detail = detailOf(parseJson(response.getBody()), status, "");
  if (status === 401) reportUnauthorized(token, detail);
  return new ApiError(status, detail);
}

/** `stack` (tus-js-client's XMLHttpRequest stack) with each PATCH's SHA-256 in Upload-Checksum, where the
 * browser has WebCrypto (secure contexts only; elsewhere the chunks go without, which tus allows). */
function checksummed(stack) {
  return {
    getName: () => `checksummed ${stack.getName()}`,
    createRequest(method, url) {
      const request = stack.createRequest(method, url);
      if (method !== "PATCH" || !(window.crypto && window.crypto.subtle)) return request;
      const send = request.send.bind(request);
      request.send = async (body) => {
        if (body) request.setHeader("Upload-Checksum", `sha256 ${await sha256Base64(body)}`);
        return send(body);
      };
      return request;
    },
  };
}

async function sha256Base64(body) {
  const bytes = body instanceof Blob ? await body.arrayBuffer() : body;
  const digest = new Uint8Array(await window.crypto.subtle.digest("SHA-256", bytes));
  let text = "";
  for (const byte of digest) text += String.fromCharCode(byte);
  return btoa(text);
}
