// ESLint flat config of the viewer: browser ES modules (no build step), Leaflet as the global `L`, tus-js-client
// as the global `tus`, GeographicLib's geodesic routines as `geodesic` and proj4js as `proj4`.
import js from "@eslint/js";
import globals from "globals";

// User-supplied strings (file names, flight names, labels, errors) are set as text, never parsed as HTML.
const AS_TEXT = "parses HTML: build nodes with h() from lib.js, or set textContent";
const LEAFLET_HTML = "Leaflet sets a string as HTML: pass a node built with h() from lib.js";
const STRING_ARGUMENT = "/^(Literal|TemplateLiteral|BinaryExpression)$/";

export default [
  { ignores: ["node_modules/"] },
  js.configs.recommended,
  {
    files: ["**/*.js"],
    languageOptions: {
      ecmaVersion: "latest",
      sourceType: "module",
      globals: { ...globals.browser, L: "readonly", tus: "readonly", geodesic: "readonly", proj4: "readonly" },
    },
    rules: {
      "no-restricted-properties": [
        "error",
        { property: "innerHTML", message: `innerHTML ${AS_TEXT}.` },
        { property: "outerHTML", message: `outerHTML ${AS_TEXT}.` },
        { property: "insertAdjacentHTML", message: `insertAdjacentHTML ${AS_TEXT}.` },
        { property: "createContextualFragment", message: `createContextualFragment ${AS_TEXT}.` },
        { property: "srcdoc", message: `srcdoc ${AS_TEXT}.` },
        { object: "document", property: "write", message: `document.write ${AS_TEXT}.` },
        { object: "document", property: "writeln", message: `document.writeln ${AS_TEXT}.` },
      ],
      "no-restricted-syntax": [
        "error",
        {
          selector: "CallExpression[callee.property.name=/^(write|writeln)$/][callee.object.property.name='document']",
          message: `window.document.write and writeln ${AS_TEXT}.`,
        },
        {
          selector: "CallExpression[callee.name='DOMParser'], NewExpression[callee.name='DOMParser']",
          message: `DOMParser ${AS_TEXT}.`,
        },
        {
          selector: `CallExpression[callee.property.name=/^(bindTooltip|bindPopup|setContent|setTooltipContent|setPopupContent)$/][arguments.0.type=${STRING_ARGUMENT}]`,
          message: `${LEAFLET_HTML}.`,
        },
        {
          selector: "CallExpression[callee.property.name='divIcon'] Property[key.name='html']",
          message: "Leaflet sets a divIcon's html as HTML: build the icon's element with h() (L.divIcon without html, then append it).",
        },
        {
          selector: `CallExpression[callee.property.name=/^(tooltip|popup)$/] Property[key.name='content'][value.type=${STRING_ARGUMENT}]`,
          message: `${LEAFLET_HTML}.`,
        },
      ],
    },
  },
];
